"""Gross errors (blunders) of the DSM on the full s2p pair, against s2p's DSM.

What is measured (the requirement): on the full ``s2p_pair`` (no ``--like``: each tool on its own
full-overlap grid, 2 workers), each DSM is placed on the grid of s2p's shipped DSM
(``expected_output/pair/dsm.tif``: EPSG:32740, 0.5 m, 721 x 739 cells, WGS84-ellipsoidal heights)
and scored after removing the median offset:

==================  ================================================================  =========
metric              definition (``e = dsm - reference - median(dsm - reference)``)    target
==================  ================================================================  =========
``gt10_pct``        share of scored cells with ``|e| > 10 m``, percent                 <= 0.01 %
``gt50_pct``        share of scored cells with ``|e| > 50 m``, percent                 0 (none)
``max_abs_m``       ``max |e|``                                                        -
``rmse_m``          ``sqrt(mean(e**2))``                                               <= 0.5 m
``nmad_m``          ``1.4826 median(|e|)`` (``e`` is already median-centred)           -
``median_m``        the median offset that was removed                                 -
``completeness``    scored cells / cells where the reference has a height              >= 0.92
==================  ================================================================  =========

"Inside the common footprint" = where the reference has a height (s2p only triangulates where both
images see the ground; its ROI is rows/cols 150-850 of img_01). Cells where the reference is NaN
are not scored at all.

Resampling (same rule as ``benchmarks/peers.py``): rioxarray ``reproject_match`` onto the reference
grid, bilinear; a reference cell has a tool height only if the tool's DSM cell under its centre
(nearest) has one, so that GDAL's bilinear does not fill one-cell holes: NaN stays NaN.

Heights: tiledsm writes WGS84-ellipsoidal heights; s2p (``out_geoid`` False, its default) too.
CARS writes EGM96 heights by default: it is run here with ``output.geoid: false`` (the
configuration of ``benchmarks/peers.py``, reused), so its DSM is ellipsoidal too and nothing is
converted. (The median-offset removal would absorb a constant N, about +2 m here, but not the
geoid's slope over the scene, a few mm over 400 m: negligible here, but the ellipsoidal output
avoids the question.)

Tools:

- tiledsm (always): ``.venv/bin/tiledsm dsm img_01.tif img_02.tif --out WORK/tiledsm/out
  --workers 2 --no-progress`` (no ``--like``: its default grid), into a freshly deleted folder
  (finished stores are resumed otherwise). ``--out-tiledsm DIR`` scores an existing output folder
  instead; ``--skip-run`` rescores ``WORK/tiledsm/out``. ``--tiledsm-rev REV`` runs the package of
  a git commit (``git archive REV tiledsm`` into ``WORK/src-<commit>``, put first on ``PYTHONPATH``
  for the client and the dask workers) instead of the working tree: a "before" baseline while
  ``tiledsm/`` is being edited. The JSON records which source ran (commit, or working tree and its
  modified files).
- peers (opt-in, ``--peers cars,s2p``), cached in ``WORK/<peer>/`` and only run when no finished
  run is there (``--rerun-peers`` forces a new run):

  - CARS 1.3.0 through ``benchmarks/peers.py`` (``run_cars``: flat initial DEM, 2 workers,
    multiprocessing, ellipsoidal output). Two rows: as delivered (CARS fills its DSM) and
    "matched cells only" (its ``filling``/``invalidity_mask`` layers applied).
  - s2p 1.0b25, full image, the configuration of ``../shared/peers.md``. Scored against the
    shipped s2p DSM, this is a *run-to-run* figure (same program; different version, tiling and
    ROI than the shipped run), not an accuracy figure.

  Install (outside the repository)::

      python3 -m venv /work/peers/cars && /work/peers/cars/bin/pip install cars==1.3.0
      # s2p: see ../shared/peers.md (apt packages, --no-deps install); venv /work/peers/s2p

Diagnosis (each tool with blunders; in full for tiledsm): connected components of the blunder
mask (8-connectivity) with their size, position, sign, distance to the footprint border (edge of
the reference's valid area), to the tool's own holes and to tiledsm's chunk seams; terrain slope
(from the reference) and image texture (std of img_01 in a 9 x 9 px window, sampled by projecting
each cell through img_01's RPC) on blunders vs good cells; tiledsm's ``confidence`` layer
(``dsm.zarr``) on blunders vs good cells, and what a confidence threshold would remove; and whether
the reference's height lies within 2 cells in the tool's own DSM (within 3 m, after the median
offset): an edge, such as a cliff's, falling a cell or two apart between the two DSMs rather than a
wrong height. A PNG per tool shows the error map with the blunders marked.

Usage::

    nice -n 10 .venv/bin/python benchmarks/blunders.py                       # tiledsm only
    nice -n 10 .venv/bin/python benchmarks/blunders.py --tiledsm-rev HEAD    # committed code, not the edits
    nice -n 10 .venv/bin/python benchmarks/blunders.py --peers cars,s2p      # + peers (cached)
    nice -n 10 .venv/bin/python benchmarks/blunders.py --skip-run            # rescore
    nice -n 10 .venv/bin/python benchmarks/blunders.py --out-tiledsm runs/x  # score a given folder

Writes ``benchmarks/results/blunders.json`` and the error maps ``WORK/blunders_<tool>.png``
(``WORK`` = ``--work``, default ``runs/bench_blunders``, git-ignored).
Exit status: 0 (scored; targets are reported, not enforced), 1 when a run failed, 2 for missing
inputs or tools.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks import peers as _peers  # noqa: E402
from benchmarks._measure import measure  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
DATA = Path(os.environ.get("TILEDSM_SHARED_DATA", REPO.parent / "shared" / "data")) / "s2p_pair"
DEFAULT_S2P = Path("/work/peers/s2p/bin/s2p")
S2P_HINT = (
    "s2p 1.0b25 lives in its own venv (see ../shared/peers.md): apt packages, then\n"
    "    python3 -m venv /work/peers/s2p && /work/peers/s2p/bin/pip install --no-deps s2p==1.0b25 && "
    "/work/peers/s2p/bin/pip install numpy scipy 'rasterio>=1.0.14' utm 'pyproj>=3' 'beautifulsoup4[lxml]' plyfile "
    "'plyflatten>=0.2.0' ransac 'rpcm>=1.4.6' 'srtm4>=1.1.2' requests\n"
    "then pass --s2p /work/peers/s2p/bin/s2p or set TILEDSM_S2P_VENV=/work/peers/s2p"
)

#: Targets of the requirement (fractions are of scored cells).
TARGETS = {"gt10_pct": 0.01, "gt50_cells": 0, "rmse_m": 0.5, "completeness": 0.92}
BLUNDER_M = 10.0
GROSS_M = 50.0
TEXTURE_WIN = 9  # px, window of the image std
BORDER_PX = 20  # "at an image / ROI edge": within this many pixels (about 10 m) of it
HOLE_CELLS = 2  # "beside a hole": within this many cells (1 m) of a no-height cell
SEAM_CELLS = 10  # "at a chunk seam": within this many tool cells of a seam between chunks
STEP_EDGE_M = 3.0  # "an edge a cell apart": the reference height found this close within HOLE_CELLS cells
#: The ROI (col, row, width, height in img_01) s2p's shipped DSM was computed in (../shared/data/README.md).
REFERENCE_ROI = (150, 150, 700, 700)


# ----------------------------------------------------------------------------------------------
# placing a DSM on the reference grid


def _open_dsm(path: Path):
    """(height, confidence or None) as 2-D rioxarray DataArrays; ``path`` is a GeoTIFF or a zarr store."""
    import rioxarray
    import xarray as xr

    if path.suffix == ".zarr":
        import warnings

        with warnings.catch_warnings():  # tiledsm's stores are not consolidated
            warnings.simplefilter("ignore", RuntimeWarning)
            ds = xr.open_zarr(path)
        if ds.rio.crs is None and "spatial_ref" in ds:
            ds = ds.rio.write_crs(ds["spatial_ref"].attrs.get("crs_wkt"))
        h = ds["height"].load()
        c = ds["confidence"].load() if "confidence" in ds else None
        return h, c
    h = rioxarray.open_rasterio(path, masked=True).squeeze("band", drop=True)
    return h, None


def on_reference_grid(dsm, ref):
    """``dsm`` (DataArray) bilinear on ``ref``'s grid; NaN where the DSM cell under a cell centre is NaN."""
    from rasterio.enums import Resampling

    dsm = dsm.astype(np.float32)
    dsm = dsm.rio.write_nodata(np.nan, encoded=False)
    bil = dsm.rio.reproject_match(ref, resampling=Resampling.bilinear, nodata=np.nan).values
    near = dsm.rio.reproject_match(ref, resampling=Resampling.nearest, nodata=np.nan).values
    return np.where(np.isfinite(near), bil, np.nan).astype(np.float64)


def nearest_on_reference_grid(layer, ref) -> np.ndarray:
    from rasterio.enums import Resampling

    layer = layer.astype(np.float32).rio.write_nodata(np.nan, encoded=False)
    return layer.rio.reproject_match(ref, resampling=Resampling.nearest, nodata=np.nan).values.astype(np.float64)


def grid_info(da) -> dict:
    t = da.rio.transform()
    return {"crs": str(da.rio.crs), "width": int(da.rio.width), "height": int(da.rio.height), "res_m": [t.a, -t.e],
            "bounds": list(da.rio.bounds())}


# ----------------------------------------------------------------------------------------------
# scores


def scores(h: np.ndarray, r: np.ndarray) -> tuple[dict, np.ndarray]:
    """Blunder statistics of ``h`` against ``r`` (same grid). Returns (scores, e) with ``e`` the
    median-centred error on the grid (NaN where not scored)."""
    ref_ok = np.isfinite(r)
    sel = ref_ok & np.isfinite(h)
    d = h[sel] - r[sel]
    n_ref, n = int(ref_ok.sum()), int(d.size)
    out = {"n_reference": n_ref, "n_scored": n, "completeness": n / max(n_ref, 1)}
    e = np.full(r.shape, np.nan)
    if not n:
        return out, e
    med = float(np.median(d))
    c = d - med
    a = np.abs(c)
    e[sel] = c
    out.update(
        median_m=med,
        gt10_cells=int((a > BLUNDER_M).sum()),
        gt50_cells=int((a > GROSS_M).sum()),
        gt10_pct=100.0 * float((a > BLUNDER_M).mean()),
        gt50_pct=100.0 * float((a > GROSS_M).mean()),
        gt3_pct=100.0 * float((a > 3.0).mean()),
        max_abs_m=float(a.max()),
        rmse_m=float(np.sqrt(np.mean(c**2))),
        rmse_without_blunders_m=float(np.sqrt(np.mean(c[a <= BLUNDER_M] ** 2))) if (a <= BLUNDER_M).any() else None,
        nmad_m=float(1.4826 * np.median(a)),
        p99_abs_m=float(np.percentile(a, 99)),
        p999_abs_m=float(np.percentile(a, 99.9)),
    )
    out["targets"] = {
        "gt10_pct<=0.01": out["gt10_pct"] <= TARGETS["gt10_pct"],
        "gt50_none": out["gt50_cells"] == TARGETS["gt50_cells"],
        "rmse<=0.5": out["rmse_m"] <= TARGETS["rmse_m"],
        "completeness>=0.92": out["completeness"] >= TARGETS["completeness"],
    }
    return out, e


# ----------------------------------------------------------------------------------------------
# diagnosis


def _slope_deg(r: np.ndarray, res: float) -> np.ndarray:
    gy, gx = np.gradient(r, res)
    return np.degrees(np.arctan(np.hypot(gx, gy)))


def project_on_images(ref, r: np.ndarray, images: list[Path], roi: tuple[int, int, int, int] | None = REFERENCE_ROI) -> dict:
    """Per reference cell, where it lands in the images (cell centre at the reference height, through
    each image's RPC, GDAL's RPC transformer): texture of images[0] there (mean and std of its grey
    levels in a TEXTURE_WIN window), distance (px) to the nearest image edge (min over the images),
    and distance (px of images[0]) to the edge of the ROI the reference was computed in. NaN where
    the reference is NaN or a projection falls outside images[0]."""
    import rasterio
    from pyproj import Transformer
    from rasterio.transform import RPCTransformer
    from scipy.ndimage import uniform_filter

    ok = np.isfinite(r)
    yy, xx = np.nonzero(ok)
    x, y = ref.rio.transform() * (xx + 0.5, yy + 0.5)
    lon, lat = Transformer.from_crs(ref.rio.crs, "EPSG:4326", always_xy=True).transform(x, y)
    out = {k: np.full(r.shape, np.nan) for k in ("img", "img_mean", "img_std", "img_edge_px", "roi_edge_px")}
    edge = np.full(yy.shape, np.inf)
    for k, path in enumerate(images):
        with rasterio.open(path) as src:
            img = src.read(1).astype(np.float64) if k == 0 else None
            rpcs, shape = src.rpcs, (src.height, src.width)
        with RPCTransformer(rpcs) as tr:
            rows, cols = tr.rowcol(lon, lat, zs=r[ok], op=np.positive)  # identity ufunc: fractional pixels
        rows, cols = np.asarray(rows, np.float64), np.asarray(cols, np.float64)
        edge = np.minimum(edge, np.minimum.reduce([rows, cols, shape[0] - rows, shape[1] - cols]))
        if k == 0:
            m = uniform_filter(img, TEXTURE_WIN)
            sd = np.sqrt(np.maximum(uniform_filter(img**2, TEXTURE_WIN) - m**2, 0))
            ri, ci = np.floor(rows).astype(np.int64), np.floor(cols).astype(np.int64)
            inside = (ri >= 0) & (ri < shape[0]) & (ci >= 0) & (ci < shape[1])
            out["img"][yy[inside], xx[inside]] = img[ri[inside], ci[inside]]
            out["img_mean"][yy[inside], xx[inside]] = m[ri[inside], ci[inside]]
            out["img_std"][yy[inside], xx[inside]] = sd[ri[inside], ci[inside]]
            if roi is not None:
                c0, r0, w, h = roi
                out["roi_edge_px"][yy, xx] = np.minimum.reduce([rows - r0, cols - c0, r0 + h - rows, c0 + w - cols])
    out["img_edge_px"][yy, xx] = edge
    return out


def _distance_to(mask_false: np.ndarray) -> np.ndarray:
    """Distance (cells) from each cell to the nearest False cell of ``mask_false`` or to the grid edge."""
    from scipy.ndimage import distance_transform_edt

    padded = np.pad(mask_false, 1, constant_values=False)
    return distance_transform_edt(padded)[1:-1, 1:-1]


def _chunk_seam_distance(ref, tool_da, chunk: int) -> np.ndarray | None:
    """Distance (tool cells) from each reference cell to the nearest seam between two chunks of
    the tool's grid (the grid's outer edges are not seams); ``inf`` when the grid has one chunk."""
    if tool_da is None or not chunk or ref.rio.crs != tool_da.rio.crs:
        return None
    rr, cc = np.mgrid[0 : ref.rio.height, 0 : ref.rio.width]
    x, y = ref.rio.transform() * (cc + 0.5, rr + 0.5)
    col, row = ~tool_da.rio.transform() * (x, y)

    def dist(v, n):
        seams = np.arange(chunk, n, chunk, dtype=np.float64)
        if not seams.size:
            return np.full(v.shape, np.inf)
        return np.abs(v[..., None] - seams).min(axis=-1)

    return np.minimum(dist(col, tool_da.rio.width), dist(row, tool_da.rio.height))


def _med(a: np.ndarray) -> float | None:
    a = a[np.isfinite(a)]
    return float(np.median(a)) if a.size else None


def speckles(h: np.ndarray, max_size: int, max_diff_m: float) -> np.ndarray:
    """Cells a speckle filter would remove: connected regions (4-neighbours whose heights differ by
    at most ``max_diff_m``) of fewer than ``max_size`` cells (OpenCV ``filterSpeckles``, heights in
    decimetres around the median)."""
    import cv2

    ok = np.isfinite(h)
    base = np.nanmedian(h)
    q = np.full(h.shape, -32768, np.int16)
    q[ok] = np.clip(np.round((h[ok] - base) * 10), -32000, 32000).astype(np.int16)
    out = q.copy()
    cv2.filterSpeckles(out, -32768, max_size, int(round(max_diff_m * 10)))
    return ok & (out == -32768)


def diagnose(e: np.ndarray, r: np.ndarray, h: np.ndarray, ref, *, conf: np.ndarray | None, geo: dict | None,
             seams: np.ndarray | None) -> dict:
    """Where the blunders (|e| > BLUNDER_M) are; see the module docstring."""
    import warnings

    from scipy.ndimage import binary_fill_holes, find_objects, label

    warnings.filterwarnings("ignore", "All-NaN slice", RuntimeWarning)
    scored = np.isfinite(e)
    bl = scored & (np.abs(e) > BLUNDER_M)
    good = scored & ~bl
    res = abs(ref.rio.transform().a)
    slope = _slope_deg(r, res)
    ref_ok = np.isfinite(r)
    # the reference's pin-holes (s2p found no height there either) vs the tool's own holes
    d_refhole = _distance_to(ref_ok | ~binary_fill_holes(ref_ok))
    d_hole = _distance_to(np.isfinite(h) | ~ref_ok)
    lab, n = label(bl, structure=np.ones((3, 3), bool))
    comps = []
    for i, sl in enumerate(find_objects(lab), start=1):
        m = lab[sl] == i
        ys, xs = np.nonzero(m)
        ys, xs = ys + sl[0].start, xs + sl[1].start
        ee = e[ys, xs]
        c = {
            "cells": int(m.sum()),
            "centroid_rc": [round(float(ys.mean()), 1), round(float(xs.mean()), 1)],
            "bbox_rc": [int(sl[0].start), int(sl[1].start), int(sl[0].stop), int(sl[1].stop)],
            "err_median_m": round(float(np.median(ee)), 1),
            "err_maxabs_m": round(float(np.abs(ee).max()), 1),
            "tool_hole_dist_min": round(float(d_hole[ys, xs].min()), 1),
            "ref_hole_dist_min": round(float(d_refhole[ys, xs].min()), 1),
            "slope_median_deg": round(float(np.nanmedian(slope[ys, xs])), 1),
        }
        if geo is not None:
            c["img_std_median"] = round(float(np.nanmedian(geo["img_std"][ys, xs])), 1)
            c["img_mean_median"] = round(float(np.nanmedian(geo["img_mean"][ys, xs])), 1)
            c["img_edge_px_min"] = round(float(np.nanmin(geo["img_edge_px"][ys, xs])), 1)
            c["roi_edge_px_min"] = round(float(np.nanmin(geo["roi_edge_px"][ys, xs])), 1)
        if conf is not None:
            c["conf_median"] = round(float(np.nanmedian(conf[ys, xs])), 3)
        if seams is not None:
            c["chunk_seam_dist_min"] = round(float(np.min(seams[ys, xs])), 1)
        comps.append(c)
    comps.sort(key=lambda c: -c["cells"])
    out: dict = {
        "blunder_cells": int(bl.sum()),
        "components": n,
        "component_sizes": [c["cells"] for c in comps],
        "largest_components": comps[:15],
        "sign": {"above_reference": int((e[bl] > 0).sum()), "below_reference": int((e[bl] < 0).sum())},
    }
    if not bl.any():
        return out

    def share(mask_fn):
        return {"blunders": float(np.mean(mask_fn(bl))), "good": float(np.mean(mask_fn(good)))}

    # the reference's height lies within HOLE_CELLS cells in the tool's own DSM: an edge (a
    # cliff, a roof) a cell or two apart between the two DSMs, not a wrong height
    offset = float(np.nanmedian(h - r - e))
    near = np.full(e.shape, np.inf)
    k = HOLE_CELLS
    hp = np.pad(h - offset, k, constant_values=np.nan)
    for di in range(-k, k + 1):
        for dj in range(-k, k + 1):
            shifted = hp[k + di: k + di + e.shape[0], k + dj: k + dj + e.shape[1]]
            near = np.fmin(near, np.abs(shifted - r))
    where = {
        f"reference_height_within_{HOLE_CELLS}_cells_in_the_tool_dsm": share(lambda m: near[m] <= STEP_EDGE_M),
        f"within_{HOLE_CELLS}_cells_of_a_tool_hole": share(lambda m: d_hole[m] <= HOLE_CELLS),
        f"within_{HOLE_CELLS}_cells_of_a_reference_hole": share(lambda m: d_refhole[m] <= HOLE_CELLS),
        "components_touching_a_tool_hole": float(np.mean([c["tool_hole_dist_min"] <= 1.5 for c in comps])),
    }
    if geo is not None:
        where[f"within_{BORDER_PX}_px_of_an_image_edge"] = share(lambda m: geo["img_edge_px"][m] <= BORDER_PX)
        where[f"within_{BORDER_PX}_px_of_the_reference_roi_edge"] = share(lambda m: geo["roi_edge_px"][m] <= BORDER_PX)
    if seams is not None:
        where[f"within_{SEAM_CELLS}_cells_of_a_chunk_seam"] = share(lambda m: seams[m] <= SEAM_CELLS)
    out["where"] = where
    out["slope_deg"] = {
        "median_blunders": _med(slope[bl]),
        "median_good": _med(slope[good]),
        "over_30deg": share(lambda m: slope[m] > 30),
    }
    if geo is not None:
        std, mean = geo["img_std"], geo["img_mean"]
        gstd = std[good][np.isfinite(std[good])]
        p10 = float(np.percentile(gstd, 10))
        out["texture"] = {
            "window_px": TEXTURE_WIN,
            "img_std_median_blunders": _med(std[bl]),
            "img_std_median_good": _med(std[good]),
            "img_mean_median_blunders": _med(mean[bl]),
            "img_mean_median_good": _med(mean[good]),
            # rank of the blunders' median std among the good cells (0.5 = typical, small = low texture)
            "blunders_std_percentile_among_good": float(np.mean(gstd < np.nanmedian(std[bl]))),
            "good_std_p10": p10,
            "in_lowest_texture_decile": share(lambda m: std[m] <= p10),
        }
    if conf is not None:
        cb, cg = conf[bl], conf[good]
        out["confidence"] = {
            "median_blunders": _med(cb),
            "median_good": _med(cg),
            "p10_good": float(np.nanpercentile(cg, 10)),
            "p90_blunders": float(np.nanpercentile(cb, 90)),
            # share of cells a threshold "confidence < t -> no height" would remove
            "threshold_effect": {f"{t:.1f}": share(lambda m, t=t: conf[m] < t) for t in (0.3, 0.4, 0.5, 0.6, 0.7, 0.8)},
        }
    try:  # would a speckle filter (as s2p/CARS use) catch them?
        sp = {}
        for size in (25, 100, 400):
            for diff in (1.0, 2.0):
                removed = speckles(h, size, diff)
                sp[f"size<{size} cells, step<={diff:g} m"] = share(lambda m, removed=removed: removed[m])
        out["speckle_filter"] = sp
    except ImportError:
        pass
    return out


def plot(path: Path, tool: str, e: np.ndarray, r: np.ndarray, conf: np.ndarray | None, geo: dict | None) -> None:
    """Error map (median removed, clipped to +-3 m) with the blunders circled; the tool's
    confidence when known; img_01 orthorectified on the reference heights with its lowest-texture
    decile outlined (without ``geo``: the reference's hillshade)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LightSource

    bl = np.isfinite(e) & (np.abs(e) > BLUNDER_M)
    ys, xs = np.nonzero(bl)
    panels = ["err"] + (["conf"] if conf is not None else []) + ["ref"]
    fig, axes = plt.subplots(1, len(panels), figsize=(6.2 * len(panels), 6.6), squeeze=False)
    for ax, name in zip(axes[0], panels):
        ax.set_facecolor("0.8")
        if name == "err":
            im = ax.imshow(np.ma.masked_invalid(e), cmap="RdBu_r", vmin=-3, vmax=3, interpolation="nearest")
            ax.set_title("error dsm - ref - median (m, clipped to +-3); grey: no height", fontsize=9)
        elif name == "conf":
            im = ax.imshow(np.ma.masked_invalid(conf), cmap="viridis", vmin=0, vmax=1, interpolation="nearest")
            ax.set_title("tiledsm confidence", fontsize=9)
        elif geo is not None and np.isfinite(geo["img"]).any():
            lo, hi = np.nanpercentile(geo["img"], [1, 99])
            ax.imshow(np.ma.masked_invalid(geo["img"]), cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
            low = np.isfinite(geo["img_std"]) & (geo["img_std"] <= np.nanpercentile(geo["img_std"], 10))
            ax.contour(low, levels=[0.5], colors="gold", linewidths=0.5)
            ax.set_title("img_01 orthorectified on the reference; gold: its lowest-texture decile", fontsize=9)
            im = None
        else:
            rr = np.where(np.isfinite(r), r, np.nanmedian(r))
            hs = LightSource(azdeg=315, altdeg=45).hillshade(rr, vert_exag=1, dx=0.5, dy=0.5)
            ax.imshow(np.ma.masked_where(~np.isfinite(r), hs), cmap="gray", interpolation="nearest")
            ax.set_title("s2p reference, hillshade", fontsize=9)
            im = None
        if im is not None:
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
        ax.scatter(xs, ys, s=16, facecolors="none", edgecolors="magenta", linewidths=0.7)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"{tool}: {bl.sum()} cells with |err| > {BLUNDER_M:g} m (magenta circles), on s2p's DSM grid", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# running the tools


def _git(*args: str) -> str | None:
    try:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


def _record(run_dir: Path) -> dict | None:
    f = run_dir / "measurement.json"
    if f.is_file():
        rec = json.loads(f.read_text())
        if rec.get("returncode") == 0:
            return rec
    return None


def export_rev(rev: str, work: Path) -> tuple[Path, str]:
    """``git archive REV tiledsm`` unpacked into ``WORK/src-<commit>``; (folder, full commit)."""
    commit = _git("rev-parse", "--verify", f"{rev}^{{commit}}")
    if not commit:
        raise SystemExit(f"blunders.py: --tiledsm-rev {rev}: not a commit")
    dest = work / f"src-{commit[:12]}"
    if not (dest / "tiledsm" / "__init__.py").is_file():
        shutil.rmtree(dest, ignore_errors=True)
        dest.mkdir(parents=True)
        archive = subprocess.run(["git", "archive", "--format=tar", commit, "tiledsm"], cwd=REPO, capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return dest, commit


def run_tiledsm(exe: Path, images: list[Path], out_dir: Path, workers: int, timeout: float, src: Path | None = None,
                source: dict | None = None) -> dict:
    """``tiledsm dsm`` into a fresh ``out_dir``; with ``src``, the package is imported from there
    (``PYTHONPATH``: ahead of the venv's editable install, in the client and in the workers)."""
    run_dir = out_dir.parent
    run_dir.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(out_dir, ignore_errors=True)  # a finished store would be resumed, not recomputed
    argv = [exe, "dsm", *images, "--out", out_dir, "--workers", str(workers), "--no-progress"]
    env = None
    if src is not None:
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(src), *filter(None, [os.environ.get("PYTHONPATH")])]))
    print(f"running: {'PYTHONPATH=' + str(src) + ' ' if src else ''}{' '.join(map(str, argv))}  (log: {run_dir / 'run.log'})", flush=True)
    m = measure(argv, env=env, log=run_dir / "run.log", timeout=timeout)
    rec = m.to_dict() | {"when": _dt.datetime.now().isoformat(timespec="seconds"), "tiledsm_source": source}
    (run_dir / "measurement.json").write_text(json.dumps(rec, indent=2))
    return rec


def find_s2p(explicit: str | None) -> Path | None:
    if explicit:
        return Path(explicit) if Path(explicit).is_file() else None
    cands = []
    if os.environ.get("TILEDSM_S2P_VENV"):
        cands.append(Path(os.environ["TILEDSM_S2P_VENV"]) / "bin" / "s2p")
    cands.append(DEFAULT_S2P)
    return next((c for c in cands if c.is_file()), None)


def run_s2p(exe: Path, images: list[Path], run_dir: Path, workers: int, timeout: float, rerun: bool) -> dict:
    """s2p 1.0b25 on the full images (config of ../shared/peers.md), cached in ``run_dir``."""
    out_dir = run_dir / "out"
    rec = None if rerun else _record(run_dir)
    if rec is None or not (out_dir / "dsm.tif").is_file():
        shutil.rmtree(out_dir, ignore_errors=True)
        run_dir.mkdir(parents=True, exist_ok=True)
        config = {
            "out_dir": str(out_dir), "images": [{"img": str(p)} for p in images],
            "horizontal_margin": 20, "vertical_margin": 5, "tile_size": 300, "disp_range_method": "sift",
            "msk_erosion": 0, "dsm_resolution": 0.5, "3d_filtering_r": 5, "3d_filtering_n": 50,
            "max_processes": workers, "full_img": True,
        }
        (run_dir / "config.json").write_text(json.dumps(config, indent=2))
        env = dict(os.environ, PATH=f"{exe.parent}:{os.environ.get('PATH', '')}")
        argv = [exe, run_dir / "config.json"]
        print(f"running: {' '.join(map(str, argv))}  (log: {run_dir / 'run.log'})", flush=True)
        m = measure(argv, cwd=run_dir, env=env, log=run_dir / "run.log", timeout=timeout)
        rec = m.to_dict() | {"when": _dt.datetime.now().isoformat(timespec="seconds")}
        (run_dir / "measurement.json").write_text(json.dumps(rec, indent=2))
    return rec


# ----------------------------------------------------------------------------------------------
# report


def format_table(rows: list[dict]) -> str:
    def f(v, fmt, w):
        return "-".rjust(w) if v is None else format(v, fmt).rjust(w)

    head = (f"{'tool':44} {'cells':>7} {'>10m %':>8} {'>50m %':>8} {'max|e| m':>9} {'RMSE m':>7} {'NMAD m':>7} "
            f"{'offset m':>9} {'compl.':>7} {'wall s':>7}")
    lines = [head, "-" * len(head)]
    for row in rows:
        s = row.get("scores") or {}
        wall = (row.get("measurement") or {}).get("wall_s")
        if row.get("error"):
            lines.append(f"{row['tool'][:44]:44} FAILED: {row['error']}")
            continue
        lines.append(
            f"{row['tool'][:44]:44} {s.get('n_scored', 0):7d} {f(s.get('gt10_pct'), '.3f', 8)} {f(s.get('gt50_pct'), '.3f', 8)} "
            f"{f(s.get('max_abs_m'), '.1f', 9)} {f(s.get('rmse_m'), '.3f', 7)} {f(s.get('nmad_m'), '.3f', 7)} "
            f"{f(s.get('median_m'), '.2f', 9)} {f(s.get('completeness'), '.3f', 7)} {f(wall, '.1f', 7)}"
        )
        c = row.get("coregistered")
        if c and "nmad" in c:
            lines.append(f"{'  after co-registration (Nuth & Kaab):':44} offset {c['offset_east_m']:+.3f} m east, "
                         f"{c['offset_north_m']:+.3f} m north; NMAD {c['nmad']:.3f} m")
    lines.append(f"{'target':44} {'':7} {'<=0.010':>8} {'0 cells':>8} {'':9} {'<=0.5':>7} {'':7} {'':9} {'>=0.92':>7}")
    return "\n".join(lines)


def format_diagnosis(tool: str, d: dict) -> str:
    def pc(v):
        return f"{100 * v:.0f} %"

    def bg(x):
        return f"{pc(x['blunders'])} of blunders vs {pc(x['good'])} of good cells"

    sizes = d["component_sizes"]
    L = [f"{tool}: {d['blunder_cells']} blunder cells (|err| > {BLUNDER_M:g} m) in {d['components']} connected components "
         f"(sizes {sizes[:15]}{' ...' if len(sizes) > 15 else ''}); {d['sign']['above_reference']} above / "
         f"{d['sign']['below_reference']} below the reference"]
    if not d["blunder_cells"]:
        return L[0]
    for k, v in d["where"].items():
        L.append(f"  {k.replace('_', ' ')}: " + (bg(v) if isinstance(v, dict) else pc(v)))
    s = d["slope_deg"]
    L.append(f"  slope (reference): median {s['median_blunders']:.1f} deg on blunders vs {s['median_good']:.1f} on good; "
             f"> 30 deg: {bg(s['over_30deg'])}")
    if "texture" in d:
        t = d["texture"]
        L.append(f"  img_01 texture (grey-level std, {t['window_px']}x{t['window_px']} px): median {t['img_std_median_blunders']:.1f} on "
                 f"blunders vs {t['img_std_median_good']:.1f} on good (percentile {100 * t['blunders_std_percentile_among_good']:.0f} of the "
                 f"good cells); lowest-texture decile (std <= {t['good_std_p10']:.1f}): {bg(t['in_lowest_texture_decile'])}; "
                 f"brightness median {t['img_mean_median_blunders']:.0f} vs {t['img_mean_median_good']:.0f}")
    if "confidence" in d:
        c = d["confidence"]
        L.append(f"  confidence: median {c['median_blunders']:.3f} on blunders vs {c['median_good']:.3f} on good "
                 f"(p90 blunders {c['p90_blunders']:.3f}, p10 good {c['p10_good']:.3f}); removing conf < t drops:")
        L.append("    " + "; ".join(f"t={t}: {pc(v['blunders'])} / {100 * v['good']:.1f} %" for t, v in c["threshold_effect"].items())
                 + "  (blunders / good)")
    if "speckle_filter" in d:
        L.append("  speckle filter on the DSM (regions of 4-neighbours with height steps <= step, smaller than size, removed): drops")
        L.append("    " + "; ".join(f"{k}: {pc(v['blunders'])} / {100 * v['good']:.1f} %" for k, v in d["speckle_filter"].items())
                 + "  (blunders / good)")
    L.append("  largest components (centroid row,col on the reference grid; min distances: tool hole / s2p hole in cells, "
             "image edge / ROI edge in px):")
    for c in d["largest_components"][:10]:
        extra = "".join(f" {k.replace('_median', '')}={c[k]}" for k in ("img_std_median", "img_mean_median", "conf_median") if k in c)
        edges = f", img edge {c['img_edge_px_min']:.0f}, ROI edge {c['roi_edge_px_min']:.0f}" if "img_edge_px_min" in c else ""
        seam = f", seam {c['chunk_seam_dist_min']:.0f}" if "chunk_seam_dist_min" in c else ""
        L.append(f"    {c['cells']:4d} cells at {c['centroid_rc']}: err {c['err_median_m']:+.1f} m (max {c['err_maxabs_m']:.0f}); "
                 f"holes {c['tool_hole_dist_min']:g}/{c['ref_hole_dist_min']:g}{edges}{seam}; slope {c['slope_median_deg']} deg;{extra}")
    return "\n".join(L)


def coregistered(h_da, reference: Path) -> dict:
    """Where the DSM lies relative to the reference (Nuth & Kääb, fitted on
    every cell) and its NMAD once moved back onto it
    (:func:`tiledsm.compare.accuracy.reference_accuracy`)."""
    from tiledsm.compare.accuracy import reference_accuracy

    stats, _ = reference_accuracy(h_da, reference, coregister=True)
    c = stats["coregistered"]
    if "error" in c:
        return {"error": c["error"], "nmad_plain": stats["nmad"]}
    return {k: c[k] for k in ("offset_east_m", "offset_north_m", "nmad", "median", "rmse", "count")} | {"nmad_plain": stats["nmad"]}


def score_tool(row: dict, dsm_path: Path, ref, r: np.ndarray, args, *, zarr_path: Path | None = None, png_name: str | None = None,
               geo: dict | None = None) -> None:
    """Fill ``row`` with scores and (for ``png_name``) a diagnosis and a PNG."""
    h_da, conf_da = _open_dsm(zarr_path if zarr_path is not None else dsm_path)
    if h_da.rio.crs is None:
        row["error"] = f"{dsm_path}: no CRS"
        return
    row["dsm"] = str(zarr_path or dsm_path)
    row["grid"] = grid_info(h_da)
    h = on_reference_grid(h_da, ref)
    row["scores"], e = scores(h, r)
    row["coregistered"] = coregistered(h_da, args.data / "expected_output" / "pair" / "dsm.tif")
    if png_name is None or "median_m" not in row["scores"]:
        return
    conf = nearest_on_reference_grid(conf_da, ref) if conf_da is not None else None
    seams = None
    if zarr_path is not None:
        chunk = (h_da.encoding.get("chunks") or (None,))[0] or args.chunk
        row["chunk"] = int(chunk)
        seams = _chunk_seam_distance(ref, h_da, int(chunk))
    row["diagnosis"] = diagnose(e, r, h, ref, conf=conf, geo=geo, seams=seams)
    png = args.work / f"blunders_{png_name}.png"
    png.parent.mkdir(parents=True, exist_ok=True)
    plot(png, row["tool"], e, r, conf, geo)
    row["png"] = str(png)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--peers", default="", help="comma-separated peers to score too: cars, s2p (opt-in; cached in --work)")
    p.add_argument("--work", type=Path, default=REPO / "runs" / "bench_blunders", help="run folders (default runs/bench_blunders)")
    p.add_argument("--skip-run", action="store_true", help="do not run tiledsm; rescore WORK/tiledsm/out (and cached peers)")
    p.add_argument("--out-tiledsm", type=Path, default=None, help="score this tiledsm output folder instead of running tiledsm")
    p.add_argument("--rerun-peers", action="store_true", help="run the peers again even when a cached run exists")
    p.add_argument("--tiledsm", default=None, help="tiledsm executable (default: next to this Python)")
    p.add_argument("--tiledsm-rev", default=None, help="run the tiledsm package of this git commit (git archive into WORK/src-<commit>, "
                   "PYTHONPATH) instead of the working tree, e.g. HEAD while tiledsm/ is being edited")
    p.add_argument("--cars", default=None, help="CARS executable (default: $TILEDSM_CARS_VENV/bin/cars or /work/peers/cars/bin/cars)")
    p.add_argument("--s2p", default=None, help="s2p executable (default: $TILEDSM_S2P_VENV/bin/s2p or /work/peers/s2p/bin/s2p)")
    p.add_argument("--data", type=Path, default=DATA, help="the s2p_pair folder")
    p.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "blunders.json")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--chunk", type=int, default=512, help="tiledsm chunk (only used to locate seams if the store does not say)")
    p.add_argument("--timeout", type=float, default=1800.0)
    p.add_argument("--no-texture", action="store_true", help="skip the image-texture diagnosis")
    args = p.parse_args(argv)
    peers = [s.strip() for s in args.peers.split(",") if s.strip()]
    if set(peers) - {"cars", "s2p"}:
        p.error(f"--peers: unknown {sorted(set(peers) - {'cars', 's2p'})} (known: cars, s2p)")

    images = [args.data / "input_pair" / "img_01.tif", args.data / "input_pair" / "img_02.tif"]
    reference = args.data / "expected_output" / "pair" / "dsm.tif"
    missing = [str(x) for x in [*images, reference] if not x.is_file()]
    if missing:
        print(f"blunders.py: missing input data: {', '.join(missing)}", file=sys.stderr)
        return 2

    import rioxarray

    ref = rioxarray.open_rasterio(reference, masked=True).squeeze("band", drop=True)
    r = ref.values.astype(np.float64)
    geo = None if args.no_texture else project_on_images(ref, r, images)

    rows: list[dict] = []
    # --- tiledsm
    import importlib.metadata

    try:
        version = importlib.metadata.version("tiledsm")
    except importlib.metadata.PackageNotFoundError:
        version = "?"
    row = {"tool": f"tiledsm {version}"}
    out_dir = args.out_tiledsm or args.work / "tiledsm" / "out"
    if args.out_tiledsm is None and not args.skip_run:
        exe = _peers.find_tiledsm(args.tiledsm)
        if exe is None:
            print("blunders.py: tiledsm executable not found; run `make install` or pass --tiledsm", file=sys.stderr)
            return 2
        src = None
        if args.tiledsm_rev:
            src, commit = export_rev(args.tiledsm_rev, args.work)
            row["tiledsm_source"] = {"rev": args.tiledsm_rev, "commit": commit, "exported_to": str(src)}
        else:
            row["tiledsm_source"] = {"working_tree": str(REPO / "tiledsm"), "head": _git("rev-parse", "HEAD"),
                                     "dirty_files": (_git("status", "--porcelain", "--", "tiledsm") or "").splitlines()}
        rec = run_tiledsm(exe, images, out_dir, args.workers, args.timeout, src, row["tiledsm_source"])
        row["command"] = " ".join(map(str, rec["argv"]))
        row["measurement"] = rec
        if rec["returncode"] != 0:
            tail = (out_dir.parent / "run.log").read_text(errors="replace").strip().splitlines()[-3:]
            row["error"] = f"exit status {rec['returncode']}: " + " | ".join(tail)
    else:
        rec = _record(out_dir.parent)  # written by this script (or peers.py) beside the out folder
        if rec is not None and "--out" in rec.get("argv", []) and Path(rec["argv"][rec["argv"].index("--out") + 1]).resolve() == out_dir.resolve():
            row["measurement"] = rec
            row["command"] = " ".join(map(str, rec["argv"]))
            row["tiledsm_source"] = rec.get("tiledsm_source")
        row["note"] = f"rescored existing output {out_dir}"
    if "error" not in row:
        tif, zarr = out_dir / "dsm.tif", out_dir / "dsm.zarr"
        if not tif.is_file() and not zarr.is_dir():
            row["error"] = f"neither {tif} nor {zarr} exists"
        else:
            metrics = out_dir / "metrics.json"
            if metrics.is_file():
                row["metrics_json_timings"] = json.loads(metrics.read_text()).get("timings")
            score_tool(row, tif, ref, r, args, zarr_path=zarr if zarr.is_dir() else None, png_name="tiledsm", geo=geo)
    rows.append(row)

    # --- peers
    if "cars" in peers:
        cars = _peers.find_cars(args.cars)
        if cars is None:
            rows.append({"tool": "CARS", "error": "not installed: " + _peers.INSTALL_HINT.replace("\n", " ")})
        else:
            ns = argparse.Namespace(reuse=not args.rerun_peers, dem_height=2320.0, resolution=0.5, workers=args.workers, timeout=args.timeout)
            run_dir = args.work / "cars"
            if args.skip_run and _record(run_dir) is None:
                crow = {"tool": "CARS", "error": f"--skip-run and no finished CARS run in {run_dir}"}
            else:
                crow = _peers.run_cars(cars, images, reference, run_dir, ns)
            crow.pop("vs_reference", None)
            crow.pop("vs_reference_matched_only", None)
            rows.append(crow)
            if "dsm" in crow and "error" not in crow:
                crow["heights"] = "WGS84 ellipsoidal (CARS output.geoid false); no conversion"
                score_tool(crow, Path(crow["dsm"]), ref, r, args, png_name="cars", geo=geo)
                matched = run_dir / "dsm_matched_only.tif"
                if matched.is_file():
                    mrow = {"tool": crow["tool"] + ", matched cells only", "note": "same run; filling != 1 or invalidity_mask != 0 set to NaN",
                            "measurement": crow.get("measurement")}
                    score_tool(mrow, matched, ref, r, args, png_name="cars_matched", geo=geo)
                    rows.append(mrow)
    if "s2p" in peers:
        s2p = find_s2p(args.s2p)
        run_dir = args.work / "s2p"
        srow = {"tool": f"s2p {_peers.venv_version(s2p, 's2p') if s2p else '?'} (run-to-run vs shipped)",
                "note": "fresh full-image s2p run scored against s2p's shipped DSM (other version, ROI and tiling): run-to-run, not accuracy"}
        if s2p is None and not (args.skip_run and (run_dir / "out" / "dsm.tif").is_file()):
            srow["error"] = "not installed: " + S2P_HINT.replace("\n", " ")
        else:
            if not args.skip_run:
                rec = run_s2p(s2p, images, run_dir, args.workers, args.timeout, args.rerun_peers)
            else:
                rec = _record(run_dir) or {}
            srow["measurement"] = rec
            srow["command"] = " ".join(map(str, rec.get("argv", [])))
            dsm = run_dir / "out" / "dsm.tif"
            if rec.get("returncode", 0) != 0 or not dsm.is_file():
                srow["error"] = f"s2p failed or no {dsm}; see {run_dir / 'run.log'}"
            else:
                srow["heights"] = "WGS84 ellipsoidal (s2p default out_geoid false)"
                score_tool(srow, dsm, ref, r, args, png_name="s2p", geo=geo)
        rows.append(srow)

    table = format_table(rows)
    print()
    print(f"s2p_pair, full overlap, each tool on its own grid ({args.workers} workers), scored on s2p's DSM grid "
          f"({reference.name}, {ref.rio.width}x{ref.rio.height}, ellipsoidal) after removing the median offset")
    print(table)
    print("cells: reference cells where the tool has a height; >10m/>50m: % of those with |err| above; "
          "compl.: share of the reference's valid cells (common footprint) with a height.")
    diags = [format_diagnosis(row["tool"], row["diagnosis"]) for row in rows if "diagnosis" in row]
    if diags:
        print()
        print("\n".join(diags))
    for row in rows:
        if "png" in row:
            print(f"error map: {row['png']}")

    dirty = _git("status", "--porcelain", "--", "tiledsm")
    result = {
        "benchmark": "blunders",
        "command": " ".join([sys.executable, *sys.argv]),
        "when": _dt.datetime.now().isoformat(timespec="seconds"),
        "host": {"node": platform.node(), "machine": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version(),
                 "load_1min": os.getloadavg()[0]},
        "tiledsm_git": {"commit": _git("rev-parse", "HEAD"), "tiledsm_dirty_files": dirty.splitlines() if dirty else []},
        "data": str(args.data),
        "reference": {"path": str(reference), "grid": grid_info(ref), "heights": "WGS84 ellipsoidal (s2p out_geoid false)"},
        "definitions": {
            "error": "e = dsm - reference - median(dsm - reference) on cells where both have a height, on the reference grid "
                     "(bilinear reproject_match; NaN if the nearest DSM cell is NaN)",
            "completeness": "cells scored / cells where the reference has a height (common footprint)",
            "nmad": "1.4826 median |e|", "rmse": "sqrt(mean e^2) after the median offset",
        },
        "targets": {"gt10_pct": "<= 0.01", "gt50": "none", "rmse_m": "<= 0.5", "completeness": ">= 0.92"},
        "rows": rows,
        "table": table,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=1, default=str))
    print(f"wrote {args.json}")
    return 1 if any(row.get("error") for row in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
