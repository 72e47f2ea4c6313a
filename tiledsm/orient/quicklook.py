"""Residual quick-look: residual vectors over each image (matplotlib
``Figure`` rendered by Agg: no pyplot, no display).

Conventions: axes are image columns (x, right) and rows (y, down), GDAL
pixel convention. Top row: before adjustment, bottom row: after; each row
exaggerates its arrows by one factor, printed in the panel titles.
"""

from __future__ import annotations

import numpy as np

__all__ = ["residual_figure"]


def _scale(vectors, size: float) -> float:
    n = np.concatenate([np.hypot(v[:, 0], v[:, 1]) for v in vectors if len(v)] or [np.zeros(0)])
    n = n[np.isfinite(n)]
    big = float(np.percentile(n, 95)) if n.size else 1.0
    return 0.08 * size / max(big, 1e-3)


def residual_figure(o, max_ties: int = 400):
    """Per image, residual vectors before (top) and after (bottom) the
    adjustment: GCPs (red), check points (blue, held out), tie points
    (green, a sample; reprojection residuals of their multi-view
    intersection). ``o`` is a :class:`~tiledsm.orient.stage.Orientation`."""
    from matplotlib.figure import Figure

    from tiledsm.orient.adjust import intersect
    from tiledsm.orient.points import point_residuals

    n = len(o.paths)
    fig = Figure(figsize=(4.2 * n, 8.4))
    rng = np.random.default_rng(0)
    size = max(max(s) for s in o.shapes)
    for row, (label, rpcs) in enumerate((("before", o.rpcs_before), ("after", o.rpcs_after))):
        ties = None
        if o.tracks is not None and o.tracks.n:
            i, p, r, c = o.tracks.observations()
            _, res = intersect(rpcs, i, p, r, c, o.tracks.n)
            ties = (i, r, c, res)
        g, ch = point_residuals(rpcs, o.gcps), point_residuals(rpcs, o.checks)
        scale = _scale([g, ch] + ([ties[3]] if ties else []), size)
        for k in range(n):
            ax = fig.add_subplot(2, n, row * n + k + 1)
            h, w = o.shapes[k]
            if ties is not None:
                i, r, c, res = ties
                sel = np.flatnonzero(i == k)
                sel = rng.choice(sel, min(max_ties, sel.size), replace=False) if sel.size else sel
                ax.quiver(c[sel], r[sel], res[sel, 1] * scale, res[sel, 0] * scale, color="green", angles="xy",
                          scale_units="xy", scale=1, width=0.002, label="tie points")
            for pts, v, colour, name in ((o.gcps, g, "red", "GCPs"), (o.checks, ch, "blue", "check points")):
                m = pts.image == k
                if m.any():
                    ax.quiver(pts.col[m], pts.row[m], v[m, 1] * scale, v[m, 0] * scale, color=colour, angles="xy",
                              scale_units="xy", scale=1, width=0.005, label=name)
            ax.set_xlim(0, w)
            ax.set_ylim(h, 0)
            ax.set_aspect("equal")
            ax.set_title(f"{o.paths[k].name} ({o.models[k].name}) {label}\narrows x{scale:.0f}", fontsize=9)
            if k == 0 and row == 0:
                ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    return fig
