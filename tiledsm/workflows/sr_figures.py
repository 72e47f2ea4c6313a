"""Quick-look of the SR -> DSM comparison: where each method's blunders are.

One panel per DSM over the hillshade of the reference: blunders
(:func:`tiledsm.workflows.sr_scores.blunder_cells`) in red, evaluated cells
without a height in magenta, the rest shaded grey. Arrays are ``(y, x)``,
row 0 at the north.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Mapping

import numpy as np

from tiledsm.io import atomic_path
from tiledsm.quicklook import NAN_COLOUR, hillshade
from tiledsm.workflows.sr_scores import BLUNDER_K, LABELS, blunder_cells

__all__ = ["blunder_map"]

BLUNDER_COLOUR = (0.9, 0.1, 0.05)


def blunder_map(heights: Mapping[str, np.ndarray], reference: np.ndarray, evaluated: np.ndarray, resolution: float,
                path: str | os.PathLike, title: str, dpi: int = 100) -> Path:
    """Write a PNG of every DSM's blunders against ``reference``, atomically.

    Parameters
    ----------
    heights : mapping of str to numpy.ndarray
        DSMs by method name (metres; NaN = no height), on the reference grid.
    reference : numpy.ndarray
        Reference heights (metres; NaN = no height): shaded under the panels.
    evaluated : numpy.ndarray
        bool, the cells that count (e.g. visible ground); a DSM's blunders
        are found on the evaluated cells where it has a height.
    resolution : float
        Cell size (metres), for the shading.
    path : path-like
        Output ``.png``.
    title : str
        Figure title (says what the reference is).

    Returns
    -------
    pathlib.Path
        The written file.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    ref = np.asarray(reference, np.float64)
    evaluated = np.asarray(evaluated, bool) & np.isfinite(ref)
    shade = np.nan_to_num(hillshade(ref, resolution), nan=0.5)
    n = len(heights)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    ny, nx = ref.shape
    fig = Figure(figsize=(4.0 * cols, 4.0 * rows * ny / max(nx, 1) + 0.9), dpi=dpi)
    for k, (name, h) in enumerate(heights.items()):
        h = np.asarray(h, np.float64)
        blunders, threshold = blunder_cells(h, ref, evaluated)
        missing = evaluated & ~np.isfinite(h)
        rgb = np.repeat((0.25 + 0.6 * shade)[..., None], 3, axis=2)
        rgb[missing] = NAN_COLOUR[:3]
        rgb[blunders] = BLUNDER_COLOUR
        scored = int(np.count_nonzero(evaluated & np.isfinite(h)))
        ax = fig.add_subplot(rows, cols, k + 1)
        ax.imshow(rgb, interpolation="nearest")
        rate = 100.0 * np.count_nonzero(blunders) / scored if scored else float("nan")
        ax.set_title(f"{LABELS.get(name, name)}: {rate:.2f} % (> {threshold:.2f} m)", fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"{title}: blunders (|error - median| > {BLUNDER_K:g} NMAD of each DSM)", fontsize=10)
    fig.legend(handles=[Patch(color=BLUNDER_COLOUR, label="blunder"), Patch(color=NAN_COLOUR[:3], label="no height")],
               loc="lower center", ncol=2, fontsize=8, frameon=False)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return path
