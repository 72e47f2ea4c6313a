"""Synthetic stereo scenes with known truth, written as GeoTIFFs.

:func:`make_scene` draws a world (:mod:`tiledsm.synth.terrain`), places 2 or
3 pushbroom views (:class:`~tiledsm.geometry.pushbroom.PushbroomCamera`)
whose along-track incidences give the asked base-to-height ratio, fits an
RPC to each (:func:`~tiledsm.geometry.fit.fit_rpc_report`), renders them
with occlusion (:mod:`tiledsm.synth.render`) and writes, under ``out_dir``:

- ``view_0.tif``, ``view_1.tif`` [``view_2.tif``]: uint16 12-bit images in
  sensor geometry, RPC tags (GDAL pixel convention), no CRS;
- ``truth_dsm.tif``: float32 surface heights (metres above the WGS84
  ellipsoid) sampled at the cell centres of a north-up UTM grid (CRS and
  transform written), ``truth_label.tif``: uint8 class (0 ground,
  1 building, 2 tree);
- visibility truth on the same grid (uint8 masks, definitions in
  :mod:`tiledsm.synth.visibility`): ``visible_{i}.tif`` (1 = the cell's
  truth point is seen by view ``i``), ``edge.tif`` (1 = 3 x 3 height range
  above ``edge_range``: walls and borders) and ``visible.tif`` (1 = seen by
  every view and not an edge cell: "visible textured ground", where DSMs
  are evaluated);
- with ``event=True``: ``post_view_*.tif``, ``post_truth_dsm.tif``,
  ``post_truth_label.tif``, the post-event masks ``post_visible.tif``,
  ``post_visible_{i}.tif``, ``post_edge.tif``, and the displacement truth
  ``dh.tif`` (post minus pre DSM), ``dx.tif``, ``dy.tif``, ``dz.tif``
  (metres; convention in :mod:`tiledsm.synth.event`);
- ``scene.json``: parameters, cameras, B/H measured from the fitted RPCs,
  RPC fit residuals, height range, paths (and the tower, if any).

With ``tower=TowerParams(...)`` the world holds one tall, narrow, flat-roofed
tower (:mod:`tiledsm.synth.tower`) whose footprint is the truth-grid window
:attr:`SceneInfo.tower_window`; every raster above includes it.

Every raster is computed tile by tile with dask (one task per chunk; a
view tile evaluates only the ground its lines of sight cross) and streamed
into the file, which is written under a temporary name and renamed at the
end: memory stays bounded whatever the size.

View layout: 2 views look at ``tan(incidence) = -bh/2`` and ``+bh/2`` along
track; with 3 views, ``view_2`` is a near-nadir view between them (so the
``view_0``/``view_1`` pair has B/H ``bh`` and each has ``bh/2`` with
``view_2``).
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from tiledsm.geometry.grid import GroundGrid
from tiledsm.geometry.pushbroom import PushbroomCamera
from tiledsm.synth.event import EventParams, evaluate_post
from tiledsm.synth.layout import DEFAULT_ROLLS, fit_view, scene_layout, view_pitches  # noqa: F401  (re-exported)
from tiledsm.synth.render import RadiometryParams, render_window
from tiledsm.synth.terrain import TerrainParams, World
from tiledsm.synth.texture import TextureParams
from tiledsm.synth.tower import Tower, TowerParams
from tiledsm.synth.visibility import VisibilityParams, visibility_window

__all__ = ["SceneInfo", "make_scene", "view_pitches"]



@dataclass(frozen=True)
class SceneInfo:
    """What :func:`make_scene` wrote and the truth it knows.

    Attributes
    ----------
    out_dir : Path
    views : tuple of Path
        ``view_*.tif``.
    truth_dsm, truth_label, scene_json : Path
    rpcs : tuple of RPC
        The fitted RPC of each view (as written in its tags).
    cameras : tuple of PushbroomCamera
        The physical cameras the RPCs were fitted to.
    grid : GroundGrid
        Grid of the truth rasters.
    origin : (float, float)
        Easting and northing of the world's local origin (metres, ``grid.crs``).
    height_range : (float, float)
        Guaranteed bounds of the surface heights, metres (ellipsoidal).
    bh : float
        B/H of the ``view_0``/``view_1`` pair, measured from the RPCs.
    bh_pairs : dict
        ``"i-j" -> B/H`` for every pair of views.
    fit_residual_px : tuple of float
        Held-out maximum RPC fit error of each view, pixels.
    visible_mask : Path
        ``visible.tif``: uint8, 1 where the cell is visible in every view
        and is not an edge cell (the cells on which DSMs are evaluated).
    visible_views : tuple of Path
        ``visible_{i}.tif``: uint8, 1 where the cell is visible in view
        ``i`` (edge cells included); see :mod:`tiledsm.synth.visibility`.
    edge_mask : Path
        ``edge.tif``: uint8, 1 on edge cells (3 x 3 height range above
        :attr:`VisibilityParams.edge_range`).
    event : dict or None
        With ``event=True``: paths of ``post_views`` (tuple), ``post_dsm``,
        ``post_label``, ``dh``, ``dx``, ``dy``, ``dz``, ``post_visible``,
        ``post_visible_views`` (tuple), ``post_edge`` (the same masks for
        the post-event surface and views); and ``params``
        (:class:`EventParams`).
    world : World
        The world itself (re-evaluable anywhere).
    timings_s : dict
        Wall time of each stage, seconds.
    tower : Tower or None
        The tower, when one was asked: truth-grid ``window``, ``footprint``
        (local metres), ``roof_height`` (metres, ellipsoidal), ``params``.
    """

    out_dir: Path
    views: tuple
    truth_dsm: Path
    truth_label: Path
    scene_json: Path
    rpcs: tuple
    cameras: tuple
    grid: GroundGrid
    origin: tuple
    height_range: tuple
    bh: float
    bh_pairs: dict
    fit_residual_px: tuple
    visible_mask: Path
    visible_views: tuple
    edge_mask: Path
    event: dict | None
    world: World = field(repr=False)
    timings_s: dict = field(default_factory=dict)
    tower: Tower | None = None

    @property
    def tower_window(self) -> tuple[int, int, int, int] | None:
        """``(row0, row1, col0, col1)``: half-open truth-grid cell ranges of
        the tower's roof (its footprint exactly), or None without a tower."""
        return None if self.tower is None else self.tower.window


# ------------------------------------------------------------------ writing
class _BlockWriter:
    """``__setitem__`` target for :func:`dask.array.store`: windowed writes
    into an open rasterio dataset, serialised by a lock."""

    def __init__(self, ds):
        self.ds = ds

    def __setitem__(self, key, value):
        from rasterio.windows import Window

        rs, cs = key
        self.ds.write(np.asarray(value), 1, window=Window(cs.start, rs.start, cs.stop - cs.start, rs.stop - rs.start))


def _store(items, *, workers=None):
    """Write dask arrays into GeoTIFFs atomically.

    ``items`` is a list of ``(dask_array, path, profile)``; all arrays are
    computed in one pass (shared tasks run once).
    """
    import contextlib

    import dask
    import dask.array as da
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning
    import warnings

    from tiledsm.io import atomic_path

    lock = threading.Lock()
    with contextlib.ExitStack() as stack:
        sources, targets = [], []
        for arr, path, profile in items:
            tmp = stack.enter_context(atomic_path(path))
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", NotGeoreferencedWarning)
                ds = stack.enter_context(rasterio.open(tmp, "w", **profile))
            sources.append(arr)
            targets.append(_BlockWriter(ds))
        with dask.config.set(scheduler="threads", num_workers=workers):
            da.store(sources, targets, lock=lock)


def raster_profile(dtype, shape, *, grid=None, rpc=None, nodata=None, block=256):
    from rasterio.rpc import RPC as RioRPC

    ny, nx = shape
    p = dict(driver="GTiff", width=nx, height=ny, count=1, dtype=np.dtype(dtype).name,
             compress="deflate", predictor=2 if np.dtype(dtype).kind in "ui" else 3, zlevel=1)
    if nx >= block and ny >= block:
        p.update(tiled=True, blockxsize=block, blockysize=block)
    if nx * ny * np.dtype(dtype).itemsize > 3_000_000_000:
        p["BIGTIFF"] = "YES"
    if nodata is not None:
        p["nodata"] = nodata
    if grid is not None:
        p.update(crs=grid.crs, transform=grid.transform)
    if rpc is not None:
        p["rpcs"] = RioRPC.from_gdal(rpc.to_gdal())
    return p


# ------------------------------------------------------------------ lazy arrays
def _image_array(ground, camera, origin, h_range, radiometry, seed, view, chunk):
    import dask.array as da

    def block(block_info=None):
        (r0, r1), (c0, c1) = block_info[None]["array-location"]
        return render_window(ground, camera, origin, h_range, (r0, r1), (c0, c1), radiometry, seed, view)

    return da.map_blocks(block, chunks=(_chunks(camera.rows, chunk), _chunks(camera.cols, chunk)),
                         dtype=np.uint16, meta=np.empty((0, 0), np.uint16))


def _chunks(n, c):
    full, rest = divmod(n, c)
    return (c,) * full + ((rest,) if rest else ())


def _grid_xy(grid: GroundGrid, origin, r0, r1, c0, c1):
    res = grid.resolution
    xs = (grid.x0 - origin[0]) + (np.arange(c0, c1) + 0.5) * res
    ys = (grid.y0 - origin[1]) - (np.arange(r0, r1) + 0.5) * res
    return xs, ys


def _truth_arrays(world, grid, origin, event_params=None):
    """Lazy stacked truth on ``grid``: (height, label) or, with an event,
    (pre height, pre label, post height, post label, dh, dx, dy, dz)."""
    import dask.array as da

    nlayer = 2 if event_params is None else 8

    def block(block_info=None):
        (r0, r1), (c0, c1) = block_info[None]["array-location"][1:]
        xs, ys = _grid_xy(grid, origin, r0, r1, c0, c1)
        h, _, lab = world.evaluate(xs, ys)
        if event_params is None:
            return np.stack([h, lab.astype(np.float32)])
        hp, _, labp, dx, dy, dz = evaluate_post(world, event_params, xs, ys)
        return np.stack([h, lab.astype(np.float32), hp, labp.astype(np.float32), hp - h, dx, dy, dz])

    rc, cc = grid.chunks
    return da.map_blocks(block, chunks=((nlayer,), rc, cc), dtype=np.float32,
                         meta=np.empty((0, 0, 0), np.float32))


def _visibility_array(ground, cameras, grid, origin, h_range, params, radiometry):
    """Lazy uint8 stack on ``grid``: visible in view 0, ..., view n-1,
    visible in all views and not edge, edge."""
    import dask.array as da

    n = len(cameras)

    def block(block_info=None):
        (r0, r1), (c0, c1) = block_info[None]["array-location"][1:]
        vis, edge = visibility_window(ground, cameras, origin, h_range, grid, (r0, r1), (c0, c1), params,
                                      radiometry)
        allv = vis.all(axis=0) & ~edge
        return np.concatenate([vis, allv[None], edge[None]]).astype(np.uint8)

    rc, cc = grid.chunks
    return da.map_blocks(block, chunks=((n + 2,), rc, cc), dtype=np.uint8, meta=np.empty((0, 0, 0), np.uint8))


# ------------------------------------------------------------------ geometry
def measured_parallax(rpc, crs: str, row: float, col: float, h: float, dh: float = 50.0) -> np.ndarray:
    """Horizontal shift (east, north; metres) of the ground point seen by
    pixel ``(row, col)`` per metre of height, measured by localising it with
    ``rpc`` at ``h - dh`` and ``h + dh`` (metres)."""
    from pyproj import Transformer

    lon, lat = rpc.localize(np.array([row, row]), np.array([col, col]), np.array([h - dh, h + dh]))
    x, y = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon, lat)
    return np.array([x[1] - x[0], y[1] - y[0]]) / (2 * dh)


# ------------------------------------------------------------------ main entry
def make_scene(
    out_dir,
    size: int = 1024,
    gsd: float = 0.5,
    bh: float = 0.4,
    seed: int = 0,
    views: int = 2,
    event: bool = False,
    chunk: int = 512,
    *,
    center: tuple[float, float] = (5.2, 44.2),
    azimuth_deg: float = 190.0,
    rolls_deg: tuple[float, ...] = DEFAULT_ROLLS,
    altitude: float = 700e3,
    terrain: TerrainParams | None = None,
    texture: TextureParams | None = None,
    radiometry: RadiometryParams | None = None,
    event_params: EventParams | None = None,
    visibility: VisibilityParams | None = None,
    tower: TowerParams | None = None,
    workers: int | None = None,
) -> SceneInfo:
    """Make a synthetic stereo scene with known truth (see module docstring).

    Parameters
    ----------
    out_dir : path-like
        Output folder (created).
    size : int
        Image size (rows = cols), pixels; the truth grid has ``size x size``
        cells of ``gsd`` metres centred on the scene.
    gsd : float
        Ground sample distance, metres.
    bh : float
        Base-to-height ratio of the ``view_0``/``view_1`` pair, in (0, 1.5].
    seed : int
        Fixes the world and the noise.
    views : int
        2 or 3.
    event : bool
        Also write the post-event scene and displacement truth.
    chunk : int
        Tile edge of the dask computation, pixels / cells.
    center : (float, float)
        Scene centre, lon/lat degrees; the CRS is its UTM zone.
    azimuth_deg, rolls_deg, altitude
        Orbit direction (degrees from grid north), per-view roll (degrees),
        orbit height (metres); see :class:`PushbroomCamera`.
    terrain, texture, radiometry, event_params, visibility : optional
        Model parameters (defaults when omitted; the event defaults scale with
        the scene extent).
    tower : TowerParams, optional
        Place one tall flat-roofed tower (default: none; a scene without
        one is the same as before towers existed).
    workers : int, optional
        Dask threads (default: one per core).

    Returns
    -------
    SceneInfo
    """
    from tiledsm.errors import TiledsmError

    if views not in (2, 3):
        raise TiledsmError(f"make_scene: views must be 2 or 3, got {views}")
    if not (0.0 < bh <= 1.5):
        raise TiledsmError(f"make_scene: bh must be in (0, 1.5], got {bh}")
    if size < 16 or gsd <= 0:
        raise TiledsmError(f"make_scene: need size >= 16 and gsd > 0, got size={size}, gsd={gsd}")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    radiometry = radiometry or RadiometryParams()
    visibility = visibility or VisibilityParams()
    lay = scene_layout(size, gsd, bh, seed, views, event, chunk, center=center, azimuth_deg=azimuth_deg,
                       rolls_deg=rolls_deg, altitude=altitude, terrain=terrain, texture=texture,
                       event_params=event_params, tower=tower)
    world, crs, origin, grid, ev, ground_post = lay.world, lay.grid.crs, lay.origin, lay.grid, lay.event, lay.post_world
    h_range, h0, cameras = lay.height_range, lay.h0, lay.cameras
    timings["world_and_cameras"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    fits = [fit_view(cam, h_range, i) for i, cam in enumerate(cameras)]
    rpcs = tuple(f[0] for f in fits)
    timings["rpc_fit"] = time.perf_counter() - t1
    par = [measured_parallax(r, crs, size / 2, size / 2, h0) for r in rpcs]
    bh_pairs = {f"{i}-{j}": float(np.linalg.norm(par[i] - par[j])) for i in range(views) for j in range(i + 1, views)}

    t1 = time.perf_counter()
    items = []
    truth = _truth_arrays(world, grid, origin, ev)
    paths = {"truth_dsm": out / "truth_dsm.tif", "truth_label": out / "truth_label.tif"}
    items.append((truth[0], paths["truth_dsm"], raster_profile(np.float32, (size, size), grid=grid)))
    items.append((truth[1].astype(np.uint8), paths["truth_label"], raster_profile(np.uint8, (size, size), grid=grid)))
    event_info = None
    if ev is not None:
        names = ("post_dsm", "post_label", "dh", "dx", "dy", "dz")
        files = ("post_truth_dsm.tif", "post_truth_label.tif", "dh.tif", "dx.tif", "dy.tif", "dz.tif")
        event_info = {"params": ev}
        for k, (name, fname) in enumerate(zip(names, files)):
            arr = truth[2 + k]
            dtype = np.uint8 if name == "post_label" else np.float32
            event_info[name] = out / fname
            items.append((arr.astype(dtype), out / fname, raster_profile(dtype, (size, size), grid=grid)))
    mask_profile = raster_profile(np.uint8, (size, size), grid=grid)

    post_cameras, post_rpcs = lay.post_cameras, rpcs
    if post_cameras is not cameras:
        post_rpcs = tuple(fit_view(c, h_range, 100 + i)[0] for i, c in enumerate(post_cameras))

    def masks(ground, prefix, cams=cameras):
        vis = _visibility_array(ground, cams, grid, origin, h_range, visibility, radiometry)
        per_view = tuple(out / f"{prefix}visible_{i}.tif" for i in range(views))
        for i, p in enumerate(per_view):
            items.append((vis[i], p, mask_profile))
        items.append((vis[views], out / f"{prefix}visible.tif", mask_profile))
        items.append((vis[views + 1], out / f"{prefix}edge.tif", mask_profile))
        return out / f"{prefix}visible.tif", per_view, out / f"{prefix}edge.tif"

    visible_mask, visible_views, edge_mask = masks(world, "")
    if ev is not None:
        m = masks(ground_post, "post_", post_cameras)
        event_info.update(post_visible=m[0], post_visible_views=m[1], post_edge=m[2])
    view_paths = []
    for i, (cam, rpc) in enumerate(zip(cameras, rpcs)):
        p = out / f"view_{i}.tif"
        view_paths.append(p)
        img = _image_array(world, cam, origin, h_range, radiometry, seed, i, chunk)
        items.append((img, p, raster_profile(np.uint16, (size, size), rpc=rpc)))
    if ev is not None:
        post_paths = []
        for i, (cam, rpc) in enumerate(zip(post_cameras, post_rpcs)):
            p = out / f"post_view_{i}.tif"
            post_paths.append(p)
            img = _image_array(ground_post, cam, origin, h_range, radiometry, seed, 100 + i, chunk)
            items.append((img, p, raster_profile(np.uint16, (size, size), rpc=rpc)))
        event_info["post_views"] = tuple(post_paths)
    _store(items, workers=workers)
    timings["render_and_write"] = time.perf_counter() - t1
    timings["total"] = time.perf_counter() - t0

    info = SceneInfo(
        out_dir=out, views=tuple(view_paths), truth_dsm=paths["truth_dsm"], truth_label=paths["truth_label"],
        scene_json=out / "scene.json", rpcs=rpcs, cameras=cameras, grid=grid, origin=origin,
        height_range=tuple(h_range), bh=bh_pairs["0-1"], bh_pairs=bh_pairs,
        fit_residual_px=tuple(f[1].check_max_px for f in fits), visible_mask=visible_mask,
        visible_views=visible_views, edge_mask=edge_mask, event=event_info, world=world,
        timings_s=timings, tower=world.tower,
    )
    _write_json(info, size=size, gsd=gsd, bh_asked=bh, seed=seed, views=views, chunk=chunk, center=center,
                radiometry=radiometry, visibility=visibility, fits=fits)
    return info


_VIS_DEFINITION = (
    "visible_i = 1 where the cell's truth point (cell centre, truth height) projects inside image i and "
    "its line of sight meets no surface between it and the sensor farther than tol_gsd * gsd metres "
    "along the ray; edge = 1 where the 3x3 truth height range exceeds edge_range metres; "
    "visible = all visible_i and not edge (uint8 masks)"
)


def _write_json(info: SceneInfo, *, fits, radiometry, visibility, **params) -> None:
    from tiledsm.io import atomic_path

    def rel(p):
        return str(Path(p).relative_to(info.out_dir))

    doc = {
        "generator": "tiledsm.synth.make_scene",
        "parameters": {k: (list(v) if isinstance(v, tuple) else v) for k, v in params.items()},
        "crs": info.grid.crs,
        "origin_en": list(info.origin),
        "truth_grid": {"x0": info.grid.x0, "y0": info.grid.y0, "resolution": info.grid.resolution,
                       "width": info.grid.width, "height": info.grid.height},
        "height_range_m": list(info.height_range),
        "heights": "metres above the WGS84 ellipsoid",
        "pixel_convention": "GDAL: top-left image corner at (0, 0), centre of pixel [i, j] at (i+0.5, j+0.5)",
        "bh_measured": info.bh,
        "bh_pairs_measured": info.bh_pairs,
        "views": [
            {
                "file": rel(p),
                "pitch_deg": cam.pitch_deg,
                "roll_deg": cam.roll_deg,
                "azimuth_deg": cam.azimuth_deg,
                "altitude_m": cam.altitude,
                "line_period_s": cam.line_period,
                "aim_point_enh": [cam.e0, cam.n0, cam.h0],
                "rpc_fit": asdict(rep) if hasattr(rep, "__dataclass_fields__") else str(rep),
            }
            for p, cam, (_, rep) in zip(info.views, info.cameras, fits)
        ],
        "radiometry": asdict(radiometry),
        "terrain": asdict(info.world.terrain),
        "texture": asdict(info.world.texture),
        "truth": {"dsm": rel(info.truth_dsm), "label": rel(info.truth_label),
                  "label_classes": {"0": "ground", "1": "building", "2": "tree"},
                  "visible_mask": rel(info.visible_mask),
                  "visible_views": [rel(p) for p in info.visible_views],
                  "edge_mask": rel(info.edge_mask),
                  "visibility": {**asdict(visibility), "definition": _VIS_DEFINITION}},
        "timings_s": info.timings_s,
    }
    if info.tower is not None:
        doc["tower"] = info.tower.to_dict(info.grid, info.origin)
    if info.event is not None:
        ev = info.event
        doc["event"] = {
            "params": asdict(ev["params"]),
            "convention": "dx, dy, dz: displacement of the ground point found at the cell after the event "
            "(it was at (x-dx, y-dy) and rose by dz); dh = post DSM - pre DSM",
            **{k: rel(v) for k, v in ev.items() if k not in ("params", "post_views", "post_visible_views")},
            "post_views": [rel(p) for p in ev["post_views"]],
            "post_visible_views": [rel(p) for p in ev["post_visible_views"]],
        }
    with atomic_path(info.scene_json) as tmp:
        Path(tmp).write_text(json.dumps(doc, indent=2))
