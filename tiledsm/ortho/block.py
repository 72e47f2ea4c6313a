"""A block of frame images read from files, for multi-image SR of orthoimages.

:func:`read_block` gathers what :class:`tiledsm.misr.methods.SRInputs`
needs from a user's files: the frames (band 1, DN), their frame cameras
from a YAML block file (:func:`tiledsm.ortho.cameras.read_cameras_yaml`),
the HR ground grid of a region, the DSM brought onto it (bilinear) and,
when one is given, a reference ortho on it (the truth the products are
scored against).

Conventions: the HR grid is north-up in the DSM's (projected) CRS, its
edges on multiples of the cell size (:meth:`GroundGrid.from_bounds`);
heights in the cameras' datum; NaN = no value.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from tiledsm.errors import GridError, InputFileError
from tiledsm.geometry.frame import FrameCamera
from tiledsm.geometry.grid import GroundGrid

__all__ = ["Block", "read_block"]


@dataclass(frozen=True)
class Block:
    """Frames, cameras and ground of a real block (:func:`read_block`).

    Attributes
    ----------
    frames : list of numpy.ndarray
        float32 DN, one per image (band 1; nodata -> NaN).
    cameras : list of FrameCamera
    names : list of str
        The image paths, in order.
    grid : GroundGrid
        HR grid of the region.
    dsm : numpy.ndarray
        Heights on ``grid`` (float64, metres).
    truth : numpy.ndarray or None
        Reference ortho on ``grid`` (float64, DN), if given.
    """

    frames: list
    cameras: list
    names: list
    grid: GroundGrid
    dsm: np.ndarray
    truth: np.ndarray | None


def _read_band(path: Path, what: str) -> np.ndarray:
    import rasterio

    from tiledsm.ortho.rectify import sensor_geometry

    try:
        with sensor_geometry(), rasterio.open(path) as src:
            a = src.read(1, masked=True)
    except (rasterio.errors.RasterioError, OSError) as exc:
        raise InputFileError(f"{path}: {what}: not a readable raster ({exc})") from None
    return np.ma.filled(a.astype(np.float32), np.nan)


def _on_grid(path: Path, grid: GroundGrid, what: str) -> np.ndarray:
    """Band 1 of a georeferenced raster resampled (bilinear) onto ``grid``;
    refused when its CRS is not the grid's or it misses part of it."""
    import rasterio
    from pyproj import CRS
    from rasterio.warp import Resampling, reproject

    try:
        src = rasterio.open(path)
    except (rasterio.errors.RasterioError, OSError) as exc:
        raise InputFileError(f"{path}: {what}: not a readable raster ({exc})") from None
    with src:
        if src.crs is None or CRS.from_user_input(src.crs) != CRS.from_user_input(grid.crs):
            raise GridError(f"{path}: {what}: CRS {src.crs} is not the cameras' {grid.crs}; reproject it first")
        left, bottom, right, top = src.bounds
        gl, gb, gr, gt = grid.bounds
        eps = 1e-6 * grid.resolution
        if gl < left - eps or gb < bottom - eps or gr > right + eps or gt > top + eps:
            raise GridError(f"{path}: {what}: covers {tuple(src.bounds)}, not the whole region {grid.bounds}")
        out = np.full(grid.shape, np.nan, np.float64)
        reproject(rasterio.band(src, 1), out, dst_transform=grid.transform, dst_crs=grid.crs,
                  resampling=Resampling.bilinear, src_nodata=src.nodata, dst_nodata=np.nan)
    return out


def read_block(
    images: Sequence[str | os.PathLike],
    cameras_file: str | os.PathLike,
    dsm: str | os.PathLike,
    bounds: Sequence[float],
    resolution: float,
    *,
    chunk: int = 64,
    truth: str | os.PathLike | None = None,
    multiple: int = 1,
) -> Block:
    """Read a block of frames for multi-image SR.

    Parameters
    ----------
    images : sequence of path
        The frames (any GDAL raster; band 1).
    cameras_file : path
        YAML block file with a camera for every image (matched by path,
        then by file name; :func:`tiledsm.ortho.cameras.camera_for_image`).
    dsm : path
        Heights in the cameras' CRS and datum, covering the region.
    bounds : (left, bottom, right, top)
        The region, in the cameras' CRS (snapped outward to ``resolution``).
    resolution : float
        HR cell, metres.
    chunk : int
        Chunk side of the grid (HR cells).
    truth : path, optional
        Reference ortho covering the region (same CRS), DN.
    multiple : int
        The grid's sides must be multiples of this (the SR scale: the LR
        grid nests in it).

    Raises
    ------
    InputFileError
        An unreadable file, an image without a camera.
    GridError
        A CRS that is not the cameras', a DSM or truth that does not cover
        the region, a region whose sides are not multiples of ``multiple``.
    """
    from tiledsm.ortho.cameras import CameraFileError, match_camera, read_cameras_yaml

    if not images:
        raise InputFileError("input.block.images: no image given")
    cams = read_cameras_yaml(cameras_file)
    cameras: list[FrameCamera] = []
    for image in images:
        try:
            cameras.append(match_camera(cams, image, cameras_file))
        except CameraFileError as exc:
            raise InputFileError(str(exc)) from None
    crs = {c.crs for c in cameras}
    if len(crs) != 1:
        raise GridError(f"{cameras_file}: the cameras use several CRS ({sorted(crs)}); one block needs one")
    grid = GroundGrid.from_bounds(crs.pop(), bounds, resolution, chunk=chunk)
    if grid.width % multiple or grid.height % multiple:
        raise GridError(f"input.block.bounds: the region is {grid.width} x {grid.height} cells of {resolution:g} m; "
                        f"both sides must be multiples of the scale {multiple}")
    frames = [_read_band(Path(p), "input.block.images") for p in images]
    height = _on_grid(Path(dsm), grid, "input.block.dsm")
    if not np.isfinite(height).any():
        raise GridError(f"{dsm}: input.block.dsm: no height in the region")
    ref = None if truth is None else _on_grid(Path(truth), grid, "input.block.truth")
    return Block(frames, cameras, [str(p) for p in images], grid, height, ref)
