"""Scores of the SR -> DSM comparison, pure functions on arrays: image
quality of an SR image against the HR one, DSM errors on the cells every
method has (a fair table) and on each method's own cells, and the
markdown report.

Conventions: heights in metres; a cell is scored when finite in every
height array compared (:func:`common_valid`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np

from tiledsm.errors import TiledsmError

__all__ = ["SRDSMError", "LABELS", "image_quality", "common_valid", "scores_on", "own_completeness", "compare_on_common",
           "common_cells_line", "markdown_report"]


class SRDSMError(TiledsmError):
    """Raised when a stage of the SR -> DSM workflow cannot run (message
    names the file or the recipe field)."""


#: how the report names each method
LABELS = {"dsm_upscale": "DSM upscale", "bicubic": "Bicubic", "srcnn": "SRCNN", "vdsr": "VDSR", "srmd": "SRMD",
          "srmd_official": "SRMD (published weights)",
          "hr": "HR pair", "lr": "LR pair"}


def image_quality(hr: np.ndarray, sr: np.ndarray, *, peak: float, border: int) -> dict:
    """PSNR (dB) and SSIM of an SR image against its HR image.

    ``hr`` is cropped to ``sr``'s shape (the SR image of an LR image of
    ``floor(n / s)`` pixels has ``s * floor(n / s)``); ``border`` pixels are
    cropped on each side; NaN pixels are ignored (see :mod:`tiledsm.sr.metrics`).
    """
    from tiledsm.sr.metrics import psnr, ssim

    hr = np.asarray(hr, np.float64)
    sr = np.asarray(sr, np.float64)
    if sr.shape[0] > hr.shape[0] or sr.shape[1] > hr.shape[1]:
        raise SRDSMError(f"SR image {sr.shape} is larger than its HR image {hr.shape}")
    hr = hr[: sr.shape[0], : sr.shape[1]]
    return {
        "psnr_db": psnr(hr, sr, data_range=peak, border=border),
        "ssim": ssim(hr, sr, data_range=peak, border=border),
        "peak": float(peak),
        "border": int(border),
    }


def common_valid(*heights: np.ndarray) -> np.ndarray:
    """Cells where every given DSM has a height.

    Parameters
    ----------
    *heights : numpy.ndarray
        Height grids of the same shape (metres; NaN = no height).

    Returns
    -------
    numpy.ndarray
        bool, True where all ``heights`` are finite.

    Raises
    ------
    ValueError
        No grid given, or grids of different shapes.
    """
    if not heights:
        raise ValueError("common_valid: at least one height grid is required")
    shape = np.shape(heights[0])
    ok = np.ones(shape, bool)
    for h in heights:
        if np.shape(h) != shape:
            raise ValueError(f"common_valid: grids of different shapes {shape} and {np.shape(h)}")
        ok &= np.isfinite(h)
    return ok


def scores_on(height: np.ndarray, reference: np.ndarray, cells: np.ndarray) -> dict:
    """Statistics of ``height - reference`` on the selected cells only.

    Parameters
    ----------
    height, reference : numpy.ndarray
        Heights on the same grid (metres; NaN = no height).
    cells : numpy.ndarray
        bool, the cells to score (e.g. :func:`common_valid`).

    Returns
    -------
    dict
        :func:`tiledsm.compare.stats.difference_statistics` of the selected
        cells: mean, median, std, rmse, mae, nmad, min, max (metres), mre
        (dimensionless ratio), count (scored cells with a height in both),
        cells (selected cells), completeness (count / cells).
    """
    from tiledsm.compare.stats import difference_statistics

    sel = np.asarray(cells, bool)
    h = np.asarray(height, np.float64)[sel]
    ref = np.asarray(reference, np.float64)[sel]
    return difference_statistics(h - ref, reference=ref)


def own_completeness(height: np.ndarray, evaluated: np.ndarray) -> dict:
    """Share of the evaluated cells where a DSM has a height.

    Parameters
    ----------
    height : numpy.ndarray
        Heights (metres; NaN = no height).
    evaluated : numpy.ndarray
        bool, the cells that count (e.g. where the reference has a height).

    Returns
    -------
    dict
        ``valid`` (cells with a height), ``cells`` (evaluated cells),
        ``completeness`` (valid / cells, a fraction in [0, 1]; NaN for no
        evaluated cell).
    """
    sel = np.asarray(evaluated, bool)
    valid = int(np.count_nonzero(np.isfinite(np.asarray(height))[sel]))
    cells = int(np.count_nonzero(sel))
    return {"valid": valid, "cells": cells, "completeness": valid / cells if cells else float("nan")}


def compare_on_common(heights: Mapping[str, np.ndarray], reference: np.ndarray,
                      mask: np.ndarray | None = None) -> dict:
    """Several DSMs against one reference, all scored on the same cells.

    The evaluated cells are those where the reference has a height (and
    ``mask`` is True); the common cells are the evaluated cells where every
    DSM of ``heights`` has a height (:func:`common_valid`).

    Parameters
    ----------
    heights : mapping of str to numpy.ndarray
        The compared DSMs by name (metres; NaN = no height), on the
        reference's grid.
    reference : numpy.ndarray
        Reference heights (metres; NaN = no height).
    mask : numpy.ndarray, optional
        bool, True = evaluate (e.g. visible ground); default every cell.

    Returns
    -------
    dict
        ``common``: ``count`` (common cells), ``cells`` (evaluated cells),
        ``fraction`` (count / cells), ``dsms`` (the names compared);
        ``scores``: per name, :func:`scores_on` the common cells (metres;
        ``count`` = common cells) with ``valid``, ``cells`` and
        ``completeness`` replaced by the DSM's own
        (:func:`own_completeness` on the evaluated cells).
    """
    ref = np.asarray(reference)
    evaluated = np.isfinite(ref)
    if mask is not None:
        evaluated &= np.asarray(mask, bool)
    common = (evaluated & common_valid(*heights.values())) if heights else evaluated
    n_common, n_eval = int(np.count_nonzero(common)), int(np.count_nonzero(evaluated))
    scores = {name: {**scores_on(h, ref, common), **own_completeness(h, evaluated)} for name, h in heights.items()}
    return {
        "common": {"count": n_common, "cells": n_eval, "fraction": n_common / n_eval if n_eval else float("nan"),
                   "dsms": list(heights)},
        "scores": scores,
    }


def _fmt(v, spec: str, scale: float = 1.0) -> str:
    if v is None or not np.isfinite(v):
        return "–"
    return format(v * scale, spec)


def common_cells_line(common: dict, reference: str) -> str:
    """The sentence under a comparison table that says which cells were scored.

    Parameters
    ----------
    common : dict
        ``common`` block of :func:`compare_on_common` (``count``, ``cells``,
        ``fraction``).
    reference : str
        What the reference is, e.g. ``"the HR-pair DSM"``.

    Returns
    -------
    str
        e.g. ``"Scored on 1234 common cells (87.5 % of the 1410 cells of
        the HR-pair DSM): ..."``.
    """
    return (f"Scored on {common['count']} common cells ({_fmt(common['fraction'], '.1f', 100)} % of the "
            f"{common['cells']} cells of {reference}): where the reference and every DSM of the table have a "
            f"height. Completeness: each DSM's own share of the {common['cells']} cells.")


def _common_lines(metrics: dict, key: str, reference: str) -> list[str]:
    """:func:`common_cells_line` and a blank line, or nothing for metrics
    written before common-cell scoring (no ``common`` block)."""
    common = metrics.get("common", {}).get(key)
    return [] if common is None else [common_cells_line(common, reference), ""]


def markdown_report(metrics: dict) -> str:
    """The run's ``report.md``: Table 1 (image quality) and Table 2 (DSM
    accuracy against the HR-pair DSM), plus Table 3 against the synthetic
    truth (visible ground) or the given reference DSM when available.

    The accuracy columns (metres; MRE in percent) of Tables 2 and 3 are on
    each table's common cells (``metrics["common"]``, see
    :func:`compare_on_common`), said in a line under the caption;
    completeness (percent) is each DSM's own."""
    m = metrics["methods"]
    sr = metrics["sr"]
    lines = [
        f"# SR -> DSM comparison: {metrics['name']}",
        "",
        f"Input: {metrics['input']}. LR pair: {sr['degrade']} x{sr['scale']} degradation of the HR pair "
        f"(RPCs regenerated); SR x{sr['scale']} with the shipped weights; every DSM on the HR grid "
        f"({metrics['grid']['resolution']:g} m, {metrics['grid']['width']} x {metrics['grid']['height']} cells).",
        "",
        f"**Table 1.** Image quality of the SR images against the HR images (mean of the two views; "
        f"PSNR peak {2 ** sr['bit_depth'] - 1} DN, {sr['border']} px border cropped).",
        "",
        "| Method | PSNR (dB) | SSIM |",
        "|---|---|---|",
    ]
    for name, r in m.items():
        if "image" in r:
            lines.append(f"| {LABELS.get(name, name)} | {_fmt(r['image']['psnr_db'], '.2f')} | {_fmt(r['image']['ssim'], '.4f')} |")
    lines += [
        "",
        "**Table 2.** DSM accuracy against the DSM of the HR pair.",
        "",
        *_common_lines(metrics, "vs_hr", "the HR-pair DSM"),
        "| Method | RMSE (m) | MRE (%) | NMAD (m) | Completeness (%) |",
        "|---|---|---|---|---|",
    ]
    for name, r in m.items():
        s = r["vs_hr"]
        lines.append(f"| {LABELS.get(name, name)} | {_fmt(s['rmse'], '.3f')} | {_fmt(s.get('mre'), '.4f', 100)} | "
                     f"{_fmt(s['nmad'], '.3f')} | {_fmt(s['completeness'], '.1f', 100)} |")
    key, title = None, None
    if "vs_truth_visible" in metrics["hr"]:
        key, title = "vs_truth_visible", "the synthetic truth, on visible ground (cells seen by both views, edges excluded)"
    elif "vs_reference" in metrics["hr"]:
        key, title = "vs_reference", f"the given reference DSM `{Path(metrics['reference']).name}`"
    if key:
        lines += [
            "",
            f"**Table 3.** DSM accuracy against {title}.",
            "",
            *_common_lines(metrics, key, "the reference"),
            "| Method | RMSE (m) | MRE (%) | NMAD (m) | Median (m) | Completeness (%) |",
            "|---|---|---|---|---|---|",
        ]
        for name, r in {"hr": metrics["hr"], **m}.items():
            s = r[key]
            lines.append(f"| {LABELS.get(name, name)} | {_fmt(s['rmse'], '.3f')} | {_fmt(s.get('mre'), '.4f', 100)} | "
                         f"{_fmt(s['nmad'], '.3f')} | {_fmt(s['median'], '+.3f')} | {_fmt(s['completeness'], '.1f', 100)} |")
    lines += ["", "Timings (s): " + ", ".join(f"{LABELS.get(k, k)} {v:.1f}" for k, v in metrics["timings"].items()), ""]
    return "\n".join(lines)
