"""Scores of the SR -> DSM comparison, pure functions on arrays: image
quality of an SR image against the HR one, DSM errors on the cells every
method has (a fair table) and on each method's own cells, and the
markdown report.

Conventions: heights in metres; a cell is scored when finite in every
height array compared (:func:`common_valid`). A blunder is a scored cell
whose error exceeds :data:`BLUNDER_K` times the NMAD of that DSM's errors
on the same cells, away from their median (:func:`blunder_cells`): a
bias is not a blunder.

The method's four-region breakdown (:func:`regions_from_truth`) needs the
synthetic truth: the class map (0 ground, 1 building, 2 tree, see
:mod:`tiledsm.synth.terrain`), the truth heights (slopes) and the
visibility mask (:mod:`tiledsm.synth.visibility`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from tiledsm.errors import TiledsmError

__all__ = ["SRDSMError", "LABELS", "BLUNDER_K", "REGIONS", "RegionRule", "image_quality", "image_quality_lazy", "common_valid", "blunder_cells",
           "scores_on", "own_completeness", "compare_on_common", "regions_from_truth", "compare_by_region",
           "common_cells_line", "markdown_report"]


class SRDSMError(TiledsmError):
    """Raised when a stage of the SR -> DSM workflow cannot run (message
    names the file or the recipe field)."""


#: how the report names each method
LABELS = {"dsm_upscale": "DSM upscale", "bicubic": "Bicubic", "srcnn": "SRCNN", "srcnn_residual": "SRCNN (residual variant)",
          "vdsr": "VDSR", "srmd": "SRMD",
          "srmd_official": "SRMD (published weights)",
          "hr": "HR pair", "lr": "LR pair"}


#: a blunder's error is farther than this many NMADs from the median error
#: (of the same DSM on the same cells)
BLUNDER_K = 3.0

#: the method's four regions, in the report's order, and how it names them
REGIONS = {"buildings": "Buildings (roofs)", "steep": "Steep terrain", "flat": "Flat ground",
           "mismatch_prone": "Mismatch-prone (trees, occlusions, edges)"}


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


def _ssim_map(ref: np.ndarray, tst: np.ndarray, *, peak: float, win_size: int) -> np.ndarray:
    """Per-window SSIM of one block (with a halo of ``win_size // 2``),
    NaN where the window touches a NaN (as :func:`tiledsm.sr.metrics.ssim`)."""
    from scipy import ndimage
    from skimage.metrics import structural_similarity

    bad = ~(np.isfinite(ref) & np.isfinite(tst))
    _, smap = structural_similarity(np.where(bad, 0.0, ref), np.where(bad, 0.0, tst), data_range=peak,
                                    win_size=win_size, full=True)
    touched = ndimage.binary_dilation(bad, structure=np.ones((win_size, win_size), bool)) if bad.any() else bad
    return np.where(touched, np.nan, smap)


def image_quality_lazy(hr, sr, *, peak: float, border: int, win_size: int = 7) -> dict:
    """:func:`image_quality` of dask arrays, block by block: PSNR from the
    sums of squared differences, SSIM as the mean of the per-window map
    (each block with a halo of ``win_size // 2``: the windows are the whole
    image's). The same values as on whole arrays, to float round-off."""
    import dask
    import dask.array as da

    hr = hr.astype(np.float64)
    sr = sr.astype(np.float64)
    if sr.shape[0] > hr.shape[0] or sr.shape[1] > hr.shape[1]:
        raise SRDSMError(f"SR image {sr.shape} is larger than its HR image {hr.shape}")
    hr = hr[: sr.shape[0], : sr.shape[1]].rechunk(sr.chunks)
    if border:
        hr, sr = hr[border:-border, border:-border], sr[border:-border, border:-border]
    pad = win_size // 2
    valid = da.isfinite(hr) & da.isfinite(sr)
    smap = da.map_overlap(_ssim_map, hr, sr, depth=pad, boundary="none", dtype=np.float64, peak=peak,
                          win_size=win_size)[pad:-pad, pad:-pad]
    sse, n, ssim_sum, ssim_n = dask.compute(da.where(valid, (hr - sr) ** 2, 0.0).sum(), valid.sum(),
                                            da.nansum(smap), da.isfinite(smap).sum())
    if not n:
        raise SRDSMError("psnr: no pixel is finite in both images")
    if not ssim_n:
        raise SRDSMError("ssim: no window free of NaN")
    mse = float(sse) / float(n)
    return {
        "psnr_db": float("inf") if mse == 0 else float(10 * np.log10(peak**2 / mse)),
        "ssim": float(ssim_sum) / float(ssim_n),
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


def blunder_cells(height: np.ndarray, reference: np.ndarray, cells: np.ndarray, k: float = BLUNDER_K) -> tuple[np.ndarray, float]:
    """The scored cells whose error is a blunder.

    Parameters
    ----------
    height, reference : numpy.ndarray
        Heights on the same grid (metres; NaN = no height).
    cells : numpy.ndarray
        bool, the cells to score.
    k : float
        Threshold in NMADs.

    Returns
    -------
    (numpy.ndarray, float)
        bool grid, True where ``cells`` holds, both heights are finite and
        ``|e - median(e)| > k * NMAD(e)``, ``e = height - reference`` over
        those cells (a robust outlier rule: a uniform bias is not a
        blunder); and the threshold ``k * NMAD`` (metres, NaN when no cell
        is scored).
    """
    from tiledsm.compare.stats import difference_statistics

    with np.errstate(invalid="ignore"):
        err = np.asarray(height, np.float64) - np.asarray(reference, np.float64)
        scored = np.asarray(cells, bool) & np.isfinite(err)
        if not scored.any():
            return np.zeros(err.shape, bool), float("nan")
        stats = difference_statistics(err[scored])
        threshold = k * stats["nmad"]
        return scored & (np.abs(err - stats["median"]) > threshold), threshold


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
        cells (selected cells), completeness (count / cells); and
        ``blunder_rate`` (fraction of the counted cells that are blunders,
        :func:`blunder_cells`) with its ``blunder_threshold`` (metres).
    """
    from tiledsm.compare.stats import difference_statistics

    sel = np.asarray(cells, bool)
    h = np.asarray(height, np.float64)[sel]
    ref = np.asarray(reference, np.float64)[sel]
    out = difference_statistics(h - ref, reference=ref)
    blunders, threshold = blunder_cells(height, reference, sel)
    n_blunders = int(np.count_nonzero(blunders))
    out["blunder_rate"] = n_blunders / out["count"] if out["count"] else float("nan")
    out["blunder_threshold"] = threshold
    return out


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


@dataclass(frozen=True)
class RegionRule:
    """Slope limits of the four-region breakdown (degrees, from the truth
    heights by central differences).

    Attributes
    ----------
    flat_max_deg : float
        Visible ground below this slope is "flat ground" (roads, fields).
    steep_min_deg : float
        Visible ground at or above it is "steep terrain". Ground between the
        two limits is in no region.
    """

    flat_max_deg: float = 10.0
    steep_min_deg: float = 25.0


def regions_from_truth(truth: np.ndarray, label: np.ndarray, visible: np.ndarray, resolution: float,
                       rule: RegionRule = RegionRule()) -> dict[str, np.ndarray]:
    """The method's four regions on a synthetic scene, disjoint.

    Parameters
    ----------
    truth : numpy.ndarray
        Truth surface heights (metres).
    label : numpy.ndarray
        Surface class: 0 ground, 1 building, 2 tree.
    visible : numpy.ndarray
        bool, seen by every view and not an edge cell (``visible.tif``).
    resolution : float
        Cell size (metres).
    rule : RegionRule
        Slope limits.

    Returns
    -------
    dict of str to numpy.ndarray
        bool masks keyed as :data:`REGIONS`: ``mismatch_prone`` = trees
        (repetitive texture that moves with the view) or cells not visible
        (occluded in a view, or walls and borders); ``buildings`` = visible
        roofs; ``steep`` / ``flat`` = visible ground by slope.
    """
    truth = np.asarray(truth, np.float64)
    label = np.asarray(label)
    visible = np.asarray(visible, bool)
    if not (truth.shape == label.shape == visible.shape):
        raise ValueError(f"regions_from_truth: shapes differ: truth {truth.shape}, label {label.shape}, visible {visible.shape}")
    gy, gx = np.gradient(truth, float(resolution))
    slope = np.degrees(np.arctan(np.hypot(gx, gy)))
    ground = visible & (label == 0)
    return {
        "buildings": visible & (label == 1),
        "steep": ground & (slope >= rule.steep_min_deg),
        "flat": ground & (slope < rule.flat_max_deg),
        "mismatch_prone": (label == 2) | ~visible,
    }


def compare_by_region(heights: Mapping[str, np.ndarray], reference: np.ndarray, regions: Mapping[str, np.ndarray]) -> dict:
    """:func:`compare_on_common` in each region (each on its own common cells).

    Returns
    -------
    dict
        region name -> :func:`compare_on_common` result.
    """
    return {name: compare_on_common(heights, reference, mask) for name, mask in regions.items()}


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


def _region_lines(regions: dict) -> list[str]:
    """Table 4: RMSE / NMAD / blunder rate per method in each region of
    the four-region breakdown, each region on its own common cells."""
    names = regions["dsms"]
    lines = [
        f"**Table 4.** Four-region breakdown against the synthetic truth ({regions['rule']}); "
        f"each cell RMSE / NMAD (m) / blunders (%, |error - median| > {BLUNDER_K:g} NMAD), on the region's common cells.",
        "",
        "| Region | Common cells | " + " | ".join(LABELS.get(n, n) for n in names) + " |",
        "|---|---|" + "---|" * len(names),
    ]
    for region, table in regions["tables"].items():
        cells = [f"{_fmt(table['scores'][n]['rmse'], '.3f')} / {_fmt(table['scores'][n]['nmad'], '.3f')} / "
                 f"{_fmt(table['scores'][n]['blunder_rate'], '.1f', 100)}" for n in names]
        lines.append(f"| {REGIONS.get(region, region)} | {table['common']['count']} | " + " | ".join(cells) + " |")
    return lines


def markdown_report(metrics: dict) -> str:
    """An ``sr_dsm`` report: Table 1 (image quality) and, when ``metrics``
    holds the DSM tables (:func:`tiledsm.evaluate.sr_dsm.with_tables`, as
    ``tiledsm evaluate`` writes ``evaluation/report.md``), Table 2 (DSM
    accuracy against the HR-pair DSM), plus Table 3 against the synthetic
    truth (visible ground) or the given reference DSM when available; a
    run's own ``report.md`` (no tables) says where they come from.

    The accuracy columns (metres; MRE in percent) of Tables 2 and 3 are on
    each table's common cells (``metrics["common"]``, see
    :func:`compare_on_common`), said in a line under the caption;
    completeness (percent) is each DSM's own. Table 4 (synthetic scenes)
    breaks the comparison with the truth down by region."""
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
    if not any("vs_hr" in r for r in m.values()):  # a run's own report: the DSMs are scored by tiledsm evaluate
        lines += ["", "DSM accuracy (Tables 2-4): `tiledsm evaluate` on this run folder writes them into "
                  "`evaluation/report.md` (and `evaluation.json`, `evaluation/blunders.png`).", ""]
    else:
        lines += [
            "",
            "**Table 2.** DSM accuracy against the DSM of the HR pair.",
            "",
            *_common_lines(metrics, "vs_hr", "the HR-pair DSM"),
            "| Method | RMSE (m) | MRE (%) | NMAD (m) | Blunders (%) | Completeness (%) |",
            "|---|---|---|---|---|---|",
        ]
        for name, r in m.items():
            s = r["vs_hr"]
            lines.append(f"| {LABELS.get(name, name)} | {_fmt(s['rmse'], '.3f')} | {_fmt(s.get('mre'), '.4f', 100)} | "
                         f"{_fmt(s['nmad'], '.3f')} | {_fmt(s.get('blunder_rate'), '.2f', 100)} | "
                         f"{_fmt(s['completeness'], '.1f', 100)} |")
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
            "| Method | RMSE (m) | MRE (%) | NMAD (m) | Median (m) | Blunders (%) | Completeness (%) |",
            "|---|---|---|---|---|---|---|",
        ]
        for name, r in {"hr": metrics["hr"], **m}.items():
            s = r[key]
            lines.append(f"| {LABELS.get(name, name)} | {_fmt(s['rmse'], '.3f')} | {_fmt(s.get('mre'), '.4f', 100)} | "
                         f"{_fmt(s['nmad'], '.3f')} | {_fmt(s['median'], '+.3f')} | {_fmt(s.get('blunder_rate'), '.2f', 100)} | "
                         f"{_fmt(s['completeness'], '.1f', 100)} |")
    if metrics.get("regions"):
        lines += ["", *_region_lines(metrics["regions"])]
    lines += ["", "Timings (s): " + ", ".join(f"{LABELS.get(k, k)} {v:.1f}" for k, v in metrics["timings"].items()), ""]
    return "\n".join(lines)
