"""Figures and the HTML report of a DSM comparison.

Figures are drawn from decimated arrays (longest edge
``output.quicklook_size``; strided, gathered by the stage in the same pass
that computes ``dh``, so no process holds a full-resolution grid) and from
the statistics' histogram, so they cost little whatever the grid size:

- ``dh``: dh over the reference hillshade, diverging colours symmetric about
  0 clipped at the 98th percentile of ``|dh|``, with colour bar;
- ``dh_hist``: histogram of dh (all valid cells and stable terrain);
- ``dh_slope_classes``: NMAD and RMSE of stable dh per slope class.

``report.html`` is self-contained (PNG figures embedded as base64).
"""

from __future__ import annotations

import base64
import html
import io
import math

import numpy as np

__all__ = ["make_figures", "write_report"]


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    return buf.getvalue()


def make_figures(dh, ref, step: int, pair, hs, part, stats, labels, spec, geoms=()) -> dict[str, bytes]:
    """PNG bytes of the three figures (see the module notes).

    ``dh`` and ``ref`` are the common grid's difference and reference
    heights strided by ``step`` cells (``a[::step, ::step]``); ``spec``
    the :class:`~tiledsm.compare.recipe.CompareSpec` of the comparison.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    from tiledsm.compare.terrain import hillshade, metric_steps

    dh = np.asarray(dh, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    ys = pair.ref.y.values[::step]
    sx, sy = metric_steps(pair.crs, pair.transform, ys)
    shade = hillshade(ref, sx * step, sy * step)
    b = pair.ref.rio.bounds()
    extent = (b[0], b[2], b[1], b[3])
    figs = {}

    fig, ax = plt.subplots(figsize=(8, 7))
    ax.imshow(np.nan_to_num(shade, nan=1.0), cmap="gray", vmin=0, vmax=1, extent=extent, interpolation="nearest")
    finite = np.isfinite(dh)
    vmax = float(np.percentile(np.abs(dh[finite]), 98)) if finite.any() else 1.0
    vmax = vmax if vmax > 0 else 1.0
    im = ax.imshow(np.ma.masked_invalid(dh), cmap="RdBu_r", vmin=-vmax, vmax=vmax, alpha=0.75, extent=extent, interpolation="nearest")
    for g in geoms:
        polys = [g["coordinates"]] if g["type"] == "Polygon" else g["coordinates"]
        for poly in polys:
            ring = np.asarray(poly[0])
            ax.plot(ring[:, 0], ring[:, 1], "k-", lw=1.0)
    ax.set_xlim(b[0], b[2])  # polygons reaching beyond the grid must not shrink the map
    ax.set_ylim(b[1], b[3])
    fig.colorbar(im, ax=ax, label="dh = other - ref (m)", shrink=0.8)
    ax.set_title(f"dh after co-registration ({spec.coreg}); black: excluded areas")
    ax.set_xlabel(f"x ({pair.crs.to_string()})")
    figs["dh"] = _png(fig)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    s_all, s_st = stats["all"], stats["stable"]
    centre = s_st["median"] if math.isfinite(s_st.get("median", float("nan"))) else 0.0
    spread = s_st["nmad"] if math.isfinite(s_st.get("nmad", float("nan"))) and s_st["nmad"] > 0 else 1.0
    lo, hi = centre - 8 * spread, centre + 8 * spread
    if math.isfinite(s_all.get("min", float("nan"))):
        lo, hi = max(lo, s_all["min"]), min(hi, s_all["max"])
        if hi <= lo:
            lo, hi = lo - 1, hi + 1
    for group, colour in (("all", "0.6"), ("stable", "C0")):
        counts, edges = hs.histogram(part, group, nbins=150, lo=lo, hi=hi)
        ax.stairs(counts, edges, fill=(group == "all"), color=colour, label=f"{group} (n={stats[group]['count']})")
    ax.set_xlabel("dh (m)")
    ax.set_ylabel("cells")
    ax.legend()
    ax.set_title(f"stable: median {s_st['median']:.3f} m, NMAD {s_st['nmad']:.3f} m, RMSE {s_st['rmse']:.3f} m")
    figs["dh_hist"] = _png(fig)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    x = np.arange(len(labels))
    nm = [stats[f"slope {lab}"]["nmad"] for lab in labels]
    rm = [stats[f"slope {lab}"]["rmse"] for lab in labels]
    ax.bar(x - 0.2, nm, 0.4, label="NMAD")
    ax.bar(x + 0.2, rm, 0.4, label="RMSE")
    ax.set_xticks(x, labels)
    ax.set_xlabel("reference slope class")
    ax.set_ylabel("m")
    ax.legend()
    ax.set_title("stable dh by slope class")
    figs["dh_slope_classes"] = _png(fig)
    plt.close(fig)
    return figs


def _fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


def _table(rows: dict, cols: list[str]) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in ["group"] + cols)
    body = "".join(
        "<tr><td>" + html.escape(name) + "</td>" + "".join(f"<td>{_fmt(r.get(c))}</td>" for c in cols) + "</tr>"
        for name, r in rows.items()
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def write_report(path, metrics: dict, figures: dict[str, bytes]) -> None:
    """Write the self-contained ``report.html``."""
    c = metrics["coregistration"]
    cols = ["count", "percent_of_valid", "mean", "median", "std", "rmse", "mae", "nmad", "mre", "min", "max"]
    creg_rows = {
        k: {"value": c.get(k)} for k in ("method", "dx_px", "dy_px", "dx", "dy", "dx_m", "dy_m", "dz", "iterations", "converged", "n_samples")
    }
    fs = c.get("fit_sample", {})
    creg_rows.update({f"fit sample {k}": {"value": v} for k, v in fs.items()})
    imgs = "".join(
        f'<figure><img src="data:image/png;base64,{base64.b64encode(png).decode()}" alt="{name}"><figcaption>{name}</figcaption></figure>'
        for name, png in figures.items()
    )
    g = metrics["grid"]
    doc = f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>tiledsm DSM comparison</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto}}table{{border-collapse:collapse;margin:1em 0}}
td,th{{border:1px solid #bbb;padding:3px 8px;text-align:right}}td:first-child{{text-align:left}}img{{max-width:100%}}</style>
</head><body>
<h1>DSM comparison</h1>
<p>reference: <code>{html.escape(str(metrics['ref']))}</code><br>other: <code>{html.escape(str(metrics['other']))}</code><br>
grid: {g['width']} x {g['height']} cells, {html.escape(g['crs'])}, {g['metres_per_pixel'][0]:.3f} x {g['metres_per_pixel'][1]:.3f} m/cell.
dh = {html.escape(metrics['dh_definition'])}.</p>
<h2>Co-registration</h2>
<p>Shift applied to the other DSM: +dx_px columns, +dy_px rows (dx, dy in CRS units; dx_m east, dy_m north in metres); dz added to its heights.</p>
{_table(creg_rows, ['value'])}
<h2>Statistics (m)</h2>
{_table(metrics['statistics'], cols + ['completeness'])}
<h2>Stable terrain by slope class (m)</h2>
{_table(metrics['slope_classes'], cols)}
<p>stable terrain: {html.escape(json_safe(metrics['stable_terrain']))}</p>
<h2>Figures</h2>{imgs}
<h2>Timings (s)</h2>{_table({k: {'s': v} for k, v in metrics.get('timings_s', {}).items()}, ['s'])}
</body></html>"""
    with open(path, "w", encoding="utf-8") as f:
        f.write(doc)


def json_safe(d) -> str:
    import json

    return json.dumps(d)
