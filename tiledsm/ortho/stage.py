"""The ortho stage: an image file + a DSM file -> ``ortho.zarr``,
``ortho.tif`` (COG), ``ortho.png`` and ``ortho.json`` in a folder.

The steps: open the image with its camera (RPC from tags/sidecar, or a
frame camera from a YAML block file, :mod:`tiledsm.ortho.cameras`), open
the DSM (GeoTIFF/COG or a tiledsm zarr store), build the lazy ortho
(:func:`tiledsm.ortho.rectify.orthorectify`), compute it chunk by chunk into
the zarr store, export the COG and the quick-look.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Sequence

import numpy as np
import xarray as xr

from tiledsm.cluster import ClusterConfig, compute_context, compute_with_progress
from tiledsm.errors import InvalidOptionError
from tiledsm.ortho.recipe import OrthoSpec
from tiledsm.ortho.rectify import ImageSource, orthorectify

__all__ = [
    "open_source", "matched_camera", "open_dsm", "resolution_factor", "ortho_files", "ortho_fingerprint",
    "write_ortho_products",
]


def matched_camera(dsm: str | Path, image: str | Path):
    """The RPC with which a tiledsm DSM store matched ``image`` (after the
    DSM stage's relative correction), or None when ``dsm`` is not a
    tiledsm ``dsm.zarr`` store or did not use ``image``.

    An ortho made on a DSM with the cameras the DSM was made with puts
    every image on the same ground: the relative pointing error the DSM
    stage removed (often ~0.5 px between Pleiades images) is removed here too.
    """
    from tiledsm.geometry.rpc import RPC
    from tiledsm.io import open_product

    p = Path(dsm)
    if not p.is_dir():
        return None
    attrs = open_product(p).attrs
    views, fp = attrs.get("views"), attrs.get("fingerprint")
    if not views or not fp:
        return None
    target = str(Path(image).resolve())
    for k, v in enumerate(views):
        if str(Path(v).resolve()) == target:
            rpcs = json.loads(fp).get("rpcs") or []
            if k < len(rpcs):
                return RPC(**rpcs[k], source=f"{target} as matched by {p}")
    return None


def open_source(image: str | Path, camera_file: str | Path | None = None, band: int = 1,
                dsm: str | Path | None = None) -> ImageSource:
    """The image and its camera: the frame camera of ``image`` in
    ``camera_file`` (YAML block file) when given; else the RPC with which
    the DSM store ``dsm`` matched it (:func:`matched_camera`); else its own RPC."""
    camera = None
    if camera_file is not None:
        from tiledsm.ortho.cameras import camera_for_image

        camera = camera_for_image(camera_file, image)
    elif dsm is not None:
        camera = matched_camera(dsm, image)
    return ImageSource.from_file(image, camera, band=band)


def open_dsm(path: str | Path) -> xr.DataArray:
    """Heights of a DSM product (GeoTIFF/COG, or a zarr store with a
    ``height`` variable), lazy."""
    from tiledsm.io import open_product

    obj = open_product(path)
    if isinstance(obj, xr.Dataset):
        if "height" not in obj:
            raise InvalidOptionError(f"--dsm: {path} has no 'height' variable (variables: {list(obj.data_vars)})")
        obj = obj["height"]
    obj.attrs.setdefault("source_path", str(path))
    return obj


def resolution_factor(dsm_resolution: float, resolution: float | None, option: str = "--resolution") -> int:
    """Integer refinement of the DSM grid giving ``resolution`` metres
    (None: 1). The ortho grid must nest in the DSM's."""
    if resolution is None:
        return 1
    if not (resolution > 0):
        raise InvalidOptionError(f"{option}: must be > 0 metres, got {resolution}")
    f = dsm_resolution / resolution
    k = int(round(f))
    if k < 1 or not math.isclose(f, k, rel_tol=1e-6):
        raise InvalidOptionError(
            f"{option}: {resolution} m does not divide the DSM's {dsm_resolution} m cells; "
            f"use {dsm_resolution:g} / k for an integer k (e.g. {dsm_resolution / max(k, 1):g})")
    return k


def ortho_files(
    image: str | Path,
    dsm: str | Path,
    params: OrthoSpec = OrthoSpec(),
    *,
    resolution: float | None = None,
    chunk: int = 512,
    camera_file: str | Path | None = None,
    bounds: tuple[float, float, float, float] | None = None,
    crs: str | None = None,
) -> xr.DataArray:
    """Lazy ortho of an image file on a DSM file with ``params`` (see
    :func:`orthorectify`); ``resolution`` (metres) must divide the DSM's
    cell size. The camera is :func:`open_source`'s (on a tiledsm
    ``dsm.zarr``, an image the DSM was made from keeps the RPC it was
    matched with)."""
    from tiledsm.io.grids import grid_like

    source = open_source(image, camera_file, dsm=dsm)
    height = open_dsm(dsm)
    factor = resolution_factor(grid_like(height).resolution, resolution)
    if chunk % factor:
        raise InvalidOptionError(f"--chunk: must be a multiple of the resolution factor {factor}, got {chunk}")
    return orthorectify(source, height, params, factor=factor, chunk=chunk, bounds=bounds, crs=crs)


def ortho_fingerprint(ortho: xr.DataArray, image: str, dsm: str, camera_file: str | None,
                      params: OrthoSpec) -> dict:
    """Everything that determines ``ortho`` (:func:`ortho_files` of these
    files), as plain JSON (:func:`tiledsm.provenance.fingerprint`): the
    identity of the image, of the DSM (a ``.zarr`` store: of its
    ``zarr.json``, which holds a tiledsm DSM's own fingerprint) and of the
    camera file; the RPC used (a sidecar's, or the one a DSM store matched
    the image with); the ortho grid and chunk; ``params`` (the kernel,
    occlusion, its tolerance and step: the ``ortho:`` section); the
    package version and code. An ``ortho.zarr`` is resumed only under the
    same fingerprint."""
    from tiledsm.geometry.rpc import RPC
    from tiledsm.provenance import fingerprint, input_identity

    dsm_file = Path(dsm) / "zarr.json" if Path(dsm).is_dir() else Path(dsm)
    camera = open_source(image, camera_file, dsm=dsm).camera
    t = ortho.rio.transform()
    return fingerprint(
        inputs={"image": input_identity(image), "dsm": input_identity(dsm_file),
                "camera": input_identity(camera_file) if camera_file else None},
        rpc=camera if isinstance(camera, RPC) else None,  # a frame camera is its file's
        grid={"crs": str(ortho.rio.crs), "transform": list(t)[:6], "shape": list(ortho.shape),
              "chunk": int(ortho.chunks[0][0])},
        params={**params.model_dump(mode="json"),
                **{k: ortho.attrs[k] for k in ("kernel", "factor", "occlusion", "halo_cells")}},
    )


def write_ortho_products(
    ortho: xr.DataArray, out: str | Path, *, cluster: ClusterConfig = ClusterConfig(), cog: bool = True,
    quicklook: bool = True, name: str = "ortho", warnings: Sequence[str] = (), resume: bool = False,
    overwrite: bool = False,
) -> dict:
    """Compute ``ortho`` into ``out/NAME.zarr``, export ``NAME.tif`` (COG)
    and ``NAME.png``, write ``NAME.json`` (attrs, valid share, timings, the
    plan's ``warnings``) last. Products of an earlier run under these names
    are withdrawn first (the report first), so an interrupted run never
    leaves an old report or export beside a new store.

    The store is written whole and atomically, or, with ``resume``, chunk
    by chunk (:func:`tiledsm.io.write_resumable`): chunks finished by an
    interrupted run of the same fingerprint (``ortho.attrs["fingerprint"]``,
    :func:`ortho_fingerprint`) are kept, only the others computed;
    ``overwrite`` discards them. Returns the report (with ``resume``, its
    ``timings.chunks`` says how many chunks were reused)."""
    from tiledsm.io import atomic_path, open_product, withdraw, write_cog, write_resumable, write_zarr
    from tiledsm.quicklook import quicklook as make_quicklook

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    withdraw(out, [f"{name}.json", f"{name}.tif", f"{name}.png"])
    t0 = time.perf_counter()
    chunks: dict = {}
    with compute_context(cluster) as client:
        def compute(d):
            return compute_with_progress(d, config=cluster, client=client)

        if resume:
            write_resumable(ortho, out / f"{name}.zarr", compute=compute, overwrite=overwrite, report=chunks)
        else:
            write_zarr(ortho, out / f"{name}.zarr", compute=compute)
    t1 = time.perf_counter()
    stored = open_product(out / f"{name}.zarr")
    if cog:
        write_cog(stored, out / f"{name}.tif")
    if quicklook:
        make_quicklook(stored, out / f"{name}.png", kind="image", title=f"{name} ({ortho.attrs.get('kernel', '')})")
    report = {
        "attrs": {k: v for k, v in ortho.attrs.items() if k != "fingerprint"},
        "shape": list(ortho.shape),
        "resolution_m": float(abs(ortho.rio.transform().a)),
        "crs": str(ortho.rio.crs),
        "valid_share": float(np.isfinite(stored.data).mean().compute()),
        "timings": {"ortho_s": t1 - t0, "export_s": time.perf_counter() - t1, **({"chunks": chunks} if chunks else {})},
        "warnings": list(warnings),
    }
    with atomic_path(out / f"{name}.json") as tmp:
        Path(tmp).write_text(json.dumps(report, indent=2, default=str))
    return report

