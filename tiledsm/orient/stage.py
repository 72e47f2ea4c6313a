"""The orientation stage: tie points, GCPs, reference DEM -> bias-corrected
RPCs, written beside copies of the images, with a residual report.

Steps (:func:`orient_images`): find every image's camera; read GCPs and
check points; multi-view tie-point tracks (:mod:`tiledsm.orient.tracks`,
P2L-filtered); one block adjustment (:mod:`tiledsm.orient.adjust`) with a
bias model per image (:mod:`tiledsm.orient.bias`); fold each image's
correction into its RPC (:func:`tiledsm.geometry.fit.with_affine`);
residuals before and after at GCPs, check points (held out of the fit) and
tie points. :func:`write_orientation` writes the products.

Conventions: pixel coordinates GDAL (top-left image corner at (0, 0)),
lon/lat WGS84 degrees, heights metres above the WGS84 ellipsoid.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from tiledsm.geometry.fit import with_affine
from tiledsm.errors import InputFileError, InvalidOptionError, MatchingError
from tiledsm.geometry.rpc import RPC
from tiledsm.orient.adjust import AdjustResult, Block, adjust_block, intersect
from tiledsm.orient.bias import TERMS, BiasModel, choose_model, get_model
from tiledsm.orient.points import ControlPoints, point_residuals, read_points
from tiledsm.orient.spec import OrientSpec
from tiledsm.orient.tracks import Tracks, tie_point_tracks

__all__ = ["Orientation", "orient_images", "write_orientation", "residual_rms"]


@dataclass(frozen=True)
class Orientation:
    """Outcome of :func:`orient_images` (everything :func:`write_orientation`
    needs)."""

    paths: tuple
    shapes: tuple
    rpcs_before: tuple
    rpcs_after: tuple
    models: tuple
    terms: tuple  # per image: dict A0..B2
    gcps: ControlPoints
    checks: ControlPoints
    tracks: Tracks | None
    adjustment: AdjustResult | None
    block: Block | None
    report: dict = field(default_factory=dict)


def residual_rms(res: np.ndarray) -> float | None:
    """RMS of the 2-D residual norms (pixels), None for none."""
    res = np.asarray(res, float).reshape(-1, 2)
    ok = np.all(np.isfinite(res), axis=1)
    return float(np.sqrt(np.mean(np.sum(res[ok] ** 2, axis=1)))) if ok.any() else None


def _choose_models(n_img: int, names: Sequence[str], gcps: ControlPoints, gcp_file: bool, n_tie: np.ndarray,
                   model: str | None) -> list[BiasModel]:
    counts = gcps.count_per_image(n_img)
    if model is not None:
        m = get_model(model)
        if gcp_file:
            short = [f"{names[i]} has {counts[i]}" for i in range(n_img) if counts[i] < m.min_gcps]
            if short:
                raise InvalidOptionError(
                    f"--model {m.name}: needs at least {m.min_gcps} GCP measurement(s) per image, but "
                    f"{'; '.join(short)} (use --model shift, which needs {get_model('shift').min_gcps}, or add GCPs)"
                )
        return [m] * n_img
    return [choose_model(int(counts[i]), int(n_tie[i])) for i in range(n_img)]


def orient_images(
    paths: Sequence[str | Path],
    gcps: str | Path | None = None,
    check_points: str | Path | None = None,
    dem=None,
    spec: OrientSpec = OrientSpec(),
    rpcs: Sequence[RPC] | None = None,
    scheduler: str | None = None,
    exclude=None,
) -> Orientation:
    """Orient a block of images (module docstring).

    Parameters
    ----------
    paths : sequence of path-like
        Images with RPCs (tags or sidecars); the first is the tie-point
        reference.
    gcps, check_points : path-like, optional
        Point files (:mod:`tiledsm.orient.points`); check points are left
        out of the fit.
    dem : callable, optional
        ``dem(lon, lat) -> h`` ellipsoidal (e.g.
        :class:`~tiledsm.orient.dem.ReferenceDEM`) constraining tie-point
        heights.
    spec : OrientSpec
        The parameters: the bias model, tie points (``tile``,
        ``extractor``, ``tracks``), the measurements' standard deviations,
        the adjustment (``adjust``), the datum. Its point-file and DEM
        fields are not read: the files are the arguments above (the plan
        resolves and opens them).
    rpcs : sequence of RPC, optional
        Cameras to use instead of those found with the images.
    scheduler : str, optional
        Dask scheduler of the tie-point tiles.
    exclude : callable, optional
        ``exclude(lon, lat) -> bool array``: True for ground that is not
        stable (e.g. a rupture zone between two epochs); tie points there
        are left out of the block (counted in the report,
        ``n_tracks_excluded``).

    Raises
    ------
    InputFileError, RPCError
        Bad images or point files.
    InvalidOptionError
        Too few GCPs for the asked model.
    MatchingError
        Nothing to adjust (no GCPs and no tie points).
    """
    import rasterio

    from tiledsm.io.cameras import find_camera

    t0 = time.perf_counter()
    paths = tuple(Path(p) for p in paths)
    if rpcs is None:
        rpcs = tuple(find_camera(p)[0] for p in paths)
    rpcs = tuple(rpcs)
    shapes = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for p in paths:
            with rasterio.open(p) as ds:
                shapes.append((ds.height, ds.width))
    names = [p.name for p in paths]
    n_img = len(paths)
    g = read_points(gcps, paths, shapes) if gcps else ControlPoints.empty()
    chk = read_points(check_points, paths, shapes) if check_points else ControlPoints.empty()
    _refuse_points_elsewhere(gcps, "--gcps", rpcs, g, shapes)
    _refuse_points_elsewhere(check_points, "--check-points", rpcs, chk, shapes)
    if len(g) and len(chk):
        both = sorted(set(g.ids.tolist()) & set(chk.ids.tolist()))
        if both:
            raise InvalidOptionError(f"--check-points: id(s) {', '.join(both[:5])} are also GCPs in {gcps}")
    timings = {"read": time.perf_counter() - t0}

    tracks = None
    guide = None
    if spec.tie_points and n_img >= 2:
        t1 = time.perf_counter()
        tracks, guide = tie_point_tracks(paths, rpcs, spec, scheduler=scheduler)
        timings["tie_points"] = time.perf_counter() - t1
    n_tie = np.isfinite(tracks.pos[..., 0]).sum(axis=1) if tracks is not None else np.zeros(n_img, int)
    if len(g) == 0 and (tracks is None or tracks.n == 0):
        raise MatchingError("orient: nothing to adjust (no GCPs and no tie points)")
    models = _choose_models(n_img, names, g, bool(gcps), n_tie, spec.model)

    # ------------------------------------------------------------ the block
    t1 = time.perf_counter()
    img_l, pt_l, row_l, col_l, sig_l = [], [], [], [], []
    ground0, prior, use_dem, ids = [], [], [], []
    n_pt = 0
    n_excluded = 0
    if tracks is not None and tracks.n:
        ti, tp, tr, tc = tracks.observations()
        h0 = 0.5 * (guide.h_range[0] + guide.h_range[1])
        gt, _ = intersect(rpcs, ti, tp, tr, tc, tracks.n, h0=h0)
        if exclude is not None:
            out = np.zeros(tracks.n, bool)
            fin = np.isfinite(gt).all(axis=1)
            out[fin] = np.asarray(exclude(gt[fin, 0], gt[fin, 1]), bool)
            gt[out] = np.nan  # dropped below with the points that did not intersect
            n_excluded = int(out.sum())
        img_l.append(ti)
        pt_l.append(tp)
        row_l.append(tr)
        col_l.append(tc)
        sig_l.append(np.full(ti.size, spec.tie_sigma_px))
        ground0.append(gt)
        prior.append(np.full(tracks.n, np.inf))
        use_dem.append(np.full(tracks.n, dem is not None))
        ids.append(np.array([f"t{k}" for k in range(tracks.n)]))
        n_pt = tracks.n
    if len(g):
        gid = g.point_ids
        index = {p: n_pt + k for k, p in enumerate(gid)}
        first = {p: int(np.flatnonzero(g.ids == p)[0]) for p in gid}
        img_l.append(g.image)
        pt_l.append(np.array([index[p] for p in g.ids.tolist()]))
        row_l.append(g.row)
        col_l.append(g.col)
        sig_l.append(np.full(len(g), spec.gcp_sigma_px))
        ground0.append(np.array([[g.lon[first[p]], g.lat[first[p]], g.h[first[p]]] for p in gid]))
        prior.append(np.full(len(gid), spec.gcp_sigma_m))
        use_dem.append(np.zeros(len(gid), bool))
        ids.append(np.array(gid))
    block = Block(
        img=np.concatenate(img_l).astype(int), pt=np.concatenate(pt_l).astype(int), row=np.concatenate(row_l),
        col=np.concatenate(col_l), sigma_px=np.concatenate(sig_l), ground0=np.vstack(ground0),
        prior_sigma_m=np.concatenate(prior), use_dem=np.concatenate(use_dem), point_ids=np.concatenate(ids),
    )
    # points seen once and without a prior carry no information
    seen = np.bincount(block.pt, minlength=block.n_points)
    bad = np.isnan(block.ground0).any(axis=1) & ~np.isfinite(block.prior_sigma_m)
    if bad.any() or (seen[~np.isfinite(block.prior_sigma_m)] < 2).any():
        keep_obs = ~bad[block.pt] & ((seen[block.pt] >= 2) | np.isfinite(block.prior_sigma_m[block.pt]))
        block = Block(block.img[keep_obs], block.pt[keep_obs], block.row[keep_obs], block.col[keep_obs],
                      block.sigma_px[keep_obs], np.nan_to_num(block.ground0), block.prior_sigma_m,
                      block.use_dem & ~bad, block.point_ids)
    slope_sigma = getattr(dem, "slope_sigma", None)  # ReferenceDEM: weight flat ground above relief
    if slope_sigma is not None and block.use_dem.any():
        block = replace(block, dem_slope_sigma_m=slope_sigma(block.ground0[:, 0], block.ground0[:, 1]))
    result = adjust_block(rpcs, models, block, dem, spec.adjust)
    timings["adjust"] = time.perf_counter() - t1
    on_gcp = np.isfinite(block.prior_sigma_m[block.pt])
    if on_gcp.any() and result.rejected[on_gcp].all():
        # the user asked for ground control and none is left: a tie-point-only result would pass for controlled
        norm = np.hypot(*result.residual_px[on_gcp].T)
        raise InputFileError(f"{gcps}: --gcps: the adjustment rejected every GCP (median residual "
                             f"{np.median(norm):.3g} px): they do not fit these images; check their coordinates "
                             "(lon/lat, ellipsoidal h) and image positions (row/col), or run without --gcps")

    # ------------------------------------------------------------ corrected RPCs
    t1 = time.perf_counter()
    datum, shift = _datum(rpcs, models, result, block, len(g) == 0 and dem is None, spec.datum)
    after, terms = [], []
    for i, (rpc, m) in enumerate(zip(rpcs, models)):
        a, b = m.full(result.x[i])
        a[0], b[0] = a[0] + shift[i, 0], b[0] + shift[i, 1]
        terms.append(dict(zip(TERMS, [float(v) for v in (*a, *b)])))
        h_range = (rpc.height_off - abs(rpc.height_scale), rpc.height_off + abs(rpc.height_scale))
        after.append(with_affine(rpc, a, b, image_shape=shapes[i], h_range=h_range,
                                     max_error=spec.refit_max_error_px).replace(
            source=f"{paths[i]} bias-corrected ({m.name})"))
    timings["fold"] = time.perf_counter() - t1
    timings["total"] = time.perf_counter() - t0

    report = _report(paths, rpcs, after, models, terms, g, chk, tracks, guide, block, result, dem)
    report["timings_s"] = timings
    report["datum"] = datum
    report["n_tracks_excluded"] = n_excluded
    return Orientation(paths, tuple(shapes), rpcs, tuple(after), tuple(models), tuple(terms), g, chk, tracks,
                       result, block, report)


def _datum(rpcs, models, result: AdjustResult, block: Block, free: bool, rule: str) -> tuple[dict, np.ndarray]:
    """How the block's datum was fixed (for orient.json) and the image shift
    ``(n, 2)`` (pixels, added to ``A0, B0``) that moves a ``free`` block
    (tie points only) onto the datum ``rule`` (:mod:`tiledsm.orient.datum`)."""
    import logging

    from tiledsm.orient.datum import DATUM_RULES, DATUMS, ground_jacobians

    shift = np.zeros((len(models), 2))
    if not free:
        return {"fixed_by": "GCPs and/or the reference DEM"}, shift
    doc = {"fixed_by": f"tie points only ({rule}): {DATUM_RULES[rule]}",
           "warning": "tie points fix only how the views agree; absolute accuracy needs GCPs (--gcps) or a "
                      "reference DEM (--dem)"}
    if DATUMS[rule] is not None:
        x = np.array([[m.full(result.x[i])[0][0], m.full(result.x[i])[1][0]] for i, m in enumerate(models)])
        measured = np.unique(block.pt[~result.rejected])  # points left out of the block sit at (0, 0)
        g = result.ground[measured]
        lon, lat, h = np.median(g[np.isfinite(g).all(axis=1)], axis=0)
        J = ground_jacobians(rpcs, lon, lat, h)
        t = DATUMS[rule](x, J)
        shift = np.einsum("nij,j->ni", J, t)
        doc.update(ground_translation_m={"east": float(t[0]), "north": float(t[1]), "up": float(t[2])},
                   shift_px=[[float(v) for v in s] for s in shift])
    logging.getLogger("tiledsm.orient").info("datum fixed by %s; %s", doc["fixed_by"], doc["warning"])
    return doc, shift


def _refuse_points_elsewhere(path, option: str, rpcs, pts: ControlPoints, shapes) -> None:
    """Refuse a point file of which no measurement projects (by its image's
    RPC) within that image's diagonal of its measured position: an RPC bias
    is pixels to tens of pixels, so such points lie in another scene (or
    have swapped lon/lat or row/col)."""
    if not len(pts):
        return
    norm = np.hypot(*point_residuals(rpcs, pts).T)
    diagonal = np.hypot(*np.asarray(shapes, float)[pts.image].T)
    if not (norm <= diagonal).any():  # NaN (no projection) counts as far
        raise InputFileError(f"{path}: {option}: no point projects within an image's size of its measured "
                             f"position (median residual {np.nanmedian(norm) if np.isfinite(norm).any() else np.nan:.3g} px): "
                             "they lie elsewhere than these images; check lon/lat, h and row/col")


def _tie_relative(rpcs, tracks: Tracks | None) -> float | None:
    if tracks is None or tracks.n == 0:
        return None
    i, p, r, c = tracks.observations()
    _, res = intersect(rpcs, i, p, r, c, tracks.n)
    return residual_rms(res)


def _report(paths, before, after, models, terms, g, chk, tracks, guide, block, result, dem) -> dict:
    rejected = result.rejected
    rej_ids = sorted({f"{block.point_ids[block.pt[j]]}@{paths[block.img[j]].name}" for j in np.flatnonzero(rejected)})
    gcp_ids = set(g.ids.tolist())
    rep = {
        "images": [],
        "gcp_rms_px": {"before": residual_rms(point_residuals(before, g)),
                       "after": residual_rms(point_residuals(after, g))},
        "check_rms_px": {"before": residual_rms(point_residuals(before, chk)),
                         "after": residual_rms(point_residuals(after, chk))},
        "tie_relative_rms_px": {"before": _tie_relative(before, tracks), "after": _tie_relative(after, tracks)},
        "rejected_gcps": sorted({r.split("@")[0] for r in rej_ids if r.split("@")[0] in gcp_ids}),
        "rejected_measurements": rej_ids if len(rej_ids) <= 200 else rej_ids[:200] + [f"... {len(rej_ids) - 200} more"],
        "n_rejected": int(rejected.sum()),
        "n_gcps": len(g.point_ids), "n_check_points": len(chk.point_ids),
        "n_tracks": 0 if tracks is None else tracks.n,
        "adjustment": {"rounds": result.rounds, "nfev": result.nfev, **result.info},
    }
    if tracks is not None:
        rep["tracks"] = {"views_per_track": np.bincount(np.isfinite(tracks.pos[..., 0]).sum(axis=0)).tolist(),
                         "rejected_p2l": list(tracks.rejected_p2l)}
    if guide is not None:
        rep["guide"] = {"h_range_m": list(guide.h_range), "shift_px": guide.shift.tolist(),
                        "coarse_matches": list(guide.n_matches)}
    if dem is not None:
        d = result.dem_residual_m[result.dem_used]
        rep["dem"] = {"source": getattr(dem, "source", str(dem)), "n_used": int(result.dem_used.sum()),
                      "median_h_minus_dem_m": float(np.median(d)) if d.size else None}
    for i, p in enumerate(paths):
        m = block.img == i
        rep["images"].append({
            "image": str(p), "model": models[i].name, "terms": terms[i],
            "n_tie_measurements": int(np.sum(m & ~np.isfinite(block.prior_sigma_m[block.pt]))),
            "n_gcp_measurements": int(np.sum(g.image == i)),
            "n_rejected": int(np.sum(rejected & m)),
            "gcp_rms_px": {"before": residual_rms(point_residuals(before, g)[g.image == i]),
                           "after": residual_rms(point_residuals(after, g)[g.image == i])},
            "check_rms_px": {"before": residual_rms(point_residuals(before, chk)[chk.image == i]),
                             "after": residual_rms(point_residuals(after, chk)[chk.image == i])},
            "rpc_before": before[i].source,
        })
    return rep


# ------------------------------------------------------------------ writing
def write_orientation(o: Orientation, out_dir: str | Path, spec: OrientSpec | None = None,
                      extra: dict | None = None) -> dict:
    """Write the products of an orientation into ``out_dir``:

    - ``<stem>_RPC.TXT``: the corrected RPC, GDAL's text format;
    - ``<stem>.tif``: a copy of the image carrying the corrected RPC in its
      tags (GDAL reads the sidecar beside it first; both hold the same
      model). Pixel coordinates are the input file's (a crop's RPC is the
      crop's: the copy has no crop geotransform);
    - ``orient.json``: terms per image, residual RMS at GCPs, check points
      and tie points before/after, rejected measurements by id, and
      (``params``) the ``spec`` the orientation ran with;
    - ``residuals.csv``: every GCP/check-point residual before/after;
    - ``residuals.png``: residual vectors over each image.

    These files of an earlier run are withdrawn first (the report first);
    ``orient.json`` is written last.

    Returns
    -------
    dict
        The ``orient.json`` document.
    """
    from tiledsm.io.cameras import rpc_txt_path, write_rpc_txt
    from tiledsm.io import atomic_path, withdraw
    from tiledsm.orient.export import copy_with_rpc
    from tiledsm.orient.quicklook import residual_figure

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    stems = [p.stem for p in o.paths]
    if len(set(stems)) != len(stems):
        raise InvalidOptionError(f"IMAGES: two images share a file stem ({', '.join(stems)}); outputs would collide")
    for p in o.paths:
        if (out / (p.stem + ".tif")).resolve() == p.resolve():
            raise InvalidOptionError(f"--out: {out} holds the input {p.name}; choose another folder")
    # an interrupted run must not leave the report of an earlier one beside new RPCs
    withdraw(out, ["orient.json", "residuals.csv", "residuals.png"]
             + [f"{s}{e}" for s in stems for e in ("_RPC.TXT", ".tif")])
    for i, p in enumerate(o.paths):
        img = out / (p.stem + ".tif")
        copy_with_rpc(p, img, o.rpcs_after[i])
        write_rpc_txt(o.rpcs_after[i], rpc_txt_path(img))
        files.append({"image": str(img), "rpc_txt": str(rpc_txt_path(img))})
    doc = dict(o.report)
    for d, f in zip(doc["images"], files):
        d.update(f)
    if spec is not None:
        doc["params"] = spec.model_dump(mode="json")
    doc.update(extra or {})
    # residual table
    rows = ["id,image,kind,row,col,drow_before,dcol_before,drow_after,dcol_after"]
    for kind, pts in (("gcp", o.gcps), ("check", o.checks)):
        rb, ra = point_residuals(o.rpcs_before, pts), point_residuals(o.rpcs_after, pts)
        for k in range(len(pts)):
            rows.append(f"{pts.ids[k]},{o.paths[pts.image[k]].name},{kind},{pts.row[k]:.3f},{pts.col[k]:.3f},"
                        f"{rb[k, 0]:.4f},{rb[k, 1]:.4f},{ra[k, 0]:.4f},{ra[k, 1]:.4f}")
    with atomic_path(out / "residuals.csv") as tmp:
        Path(tmp).write_text("\n".join(rows) + "\n")
    with atomic_path(out / "residuals.png") as tmp:
        residual_figure(o).savefig(tmp, format="png", dpi=100)
    with atomic_path(out / "orient.json") as tmp:
        Path(tmp).write_text(json.dumps(doc, indent=2, default=_json_default))
    return doc


def _json_default(v):
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return float(v)
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)
