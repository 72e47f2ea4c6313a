"""Synthetic orientation problems with known truth: pushbroom RPCs, injected
biases, GCPs and tie correspondences (no rendering). Used by the tests and
``benchmarks/orient.py``.

Conventions: pixel coordinates GDAL (top-left image corner at (0, 0)),
lon/lat WGS84 degrees, heights metres above the WGS84 ellipsoid.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from tiledsm.geometry.fit import with_affine
from tiledsm.geometry.rpc import RPC

__all__ = ["pushbroom_rpcs", "invert_affine", "inject_bias", "ground_points", "project_all", "write_points_csv",
           "biased_copies", "corner_points", "synthetic_block"]


def pushbroom_rpcs(
    views: int = 2,
    size: int = 1024,
    gsd: float = 0.5,
    bh: float = 0.4,
    center: tuple[float, float] = (5.2, 44.2),
    h_range: tuple[float, float] = (200.0, 400.0),
) -> list[RPC]:
    """RPCs fitted to the pushbroom views :func:`tiledsm.synth.make_scene`
    would place (same pitches and rolls), without rendering anything."""
    from pyproj import Transformer

    from tiledsm.geometry.fit import fit_rpc
    from tiledsm.geometry.grid import utm_crs
    from tiledsm.geometry.pushbroom import PushbroomCamera
    from tiledsm.synth.scene import DEFAULT_ROLLS, view_pitches

    crs = utm_crs(*center)
    e0, n0 = Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(*center)
    h0 = 0.5 * (h_range[0] + h_range[1])
    out = []
    for i, p in enumerate(view_pitches(bh, views)):
        cam = PushbroomCamera(crs, e0, n0, h0, size, size, gsd, pitch_deg=p, roll_deg=DEFAULT_ROLLS[i])
        r = np.array([0, 0, size, size] * 2, float)
        c = np.array([0, size, 0, size] * 2, float)
        lon, lat = cam.localize(r, c, np.repeat(np.asarray(h_range, float), 4))
        dlon, dlat = 0.02 * np.ptp(lon), 0.02 * np.ptp(lat)
        out.append(fit_rpc(cam.project, (lon.min() - dlon, lon.max() + dlon), (lat.min() - dlat, lat.max() + dlat),
                           tuple(h_range), (size, size), source=f"synthetic pushbroom view_{i}"))
    return out


def invert_affine(a: Sequence[float], b: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Terms ``(A', B')`` of the inverse map: if ``r = l + A0 + A1 l + A2 s``
    (and the sample equation) then ``l = r + A0' + A1' r + A2' c``."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    k = np.array([[1 + a[1], a[2]], [b[1], 1 + b[2]]])
    ki = np.linalg.inv(k)
    t = -ki @ np.array([a[0], b[0]])
    lin = ki - np.eye(2)
    return np.array([t[0], lin[0, 0], lin[0, 1]]), np.array([t[1], lin[1, 0], lin[1, 1]])


def inject_bias(rpc: RPC, a, b, shape: tuple[int, int], h_range: tuple[float, float]) -> RPC:
    """A biased copy of ``rpc``: it projects a ground point whose true
    position is ``(l, s)`` to ``(l + A0 + A1 l + A2 s, s + B0 + B1 l + B2 s)``,
    so that :func:`~tiledsm.orient.adjust.adjust_block` should find
    ``(a, b)`` (the model of :mod:`tiledsm.orient.bias`)."""
    ia, ib = invert_affine(a, b)
    return with_affine(rpc, ia, ib, image_shape=shape, h_range=h_range, max_error=0.005)


def ground_points(rpc: RPC, shape: tuple[int, int], h_range: tuple[float, float], n: int, seed: int = 0,
                  margin: float = 0.05):
    """``n`` random ground points seen by ``rpc`` inside the image (less a
    ``margin`` fraction on each side), heights uniform in ``h_range``."""
    rng = np.random.default_rng(seed)
    rows = rng.uniform(margin, 1 - margin, n) * shape[0]
    cols = rng.uniform(margin, 1 - margin, n) * shape[1]
    h = rng.uniform(*h_range, n)
    lon, lat = rpc.localize(rows, cols, h)
    return lon, lat, h


def project_all(rpcs: Sequence[RPC], lon, lat, h) -> np.ndarray:
    """``(views, n, 2)`` row/col of the points in every view."""
    return np.stack([np.stack(r.project(lon, lat, h), -1) for r in rpcs])


def write_points_csv(path, names: Sequence[str], rpcs: Sequence[RPC], lon, lat, h, prefix: str = "g",
                     noise_px: float = 0.0, seed: int = 0, shape: tuple[int, int] | None = None) -> None:
    """A GCP / check-point CSV (``id,image,lon,lat,h,row,col``) of ground
    points measured in every image where ``rpcs`` (the true cameras) sees
    them (inside ``shape`` when given), with Gaussian noise of
    ``noise_px`` pixels per axis."""
    rng = np.random.default_rng(seed)
    lines = ["id,image,lon,lat,h,row,col"]
    for k in range(len(lon)):
        for name, rpc in zip(names, rpcs):
            r, c = (float(v) for v in rpc.project(lon[k], lat[k], h[k]))
            x, y, z = float(lon[k]), float(lat[k]), float(h[k])
            r += rng.normal(0, noise_px) if noise_px else 0.0
            c += rng.normal(0, noise_px) if noise_px else 0.0
            if shape is not None and not (0 <= r <= shape[0] and 0 <= c <= shape[1]):
                continue
            lines.append(f"{prefix}{k},{name},{x!r},{y!r},{z!r},{r!r},{c!r}")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def biased_copies(paths: Sequence, rpcs: Sequence[RPC], biases: Sequence, out_dir, h_range) -> list:
    """Copies of the images into ``out_dir`` whose RPC tags are
    :func:`inject_bias` of ``rpcs`` with ``biases[i] = (a, b)``."""
    from pathlib import Path

    import rasterio

    from tiledsm.orient.export import copy_with_rpc

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    res = []
    for p, rpc, (a, b) in zip(paths, rpcs, biases):
        with rasterio.open(p) as ds:
            shape = (ds.height, ds.width)
        dst = out / Path(p).name
        copy_with_rpc(p, dst, inject_bias(rpc, a, b, shape, h_range))
        res.append(dst)
    return res


def corner_points(rpc: RPC, shape: tuple[int, int], h_range: tuple[float, float], margin: float = 0.1,
                  seed: int = 0):
    """Four ground points near the image corners (``margin`` fraction
    inside), heights uniform in ``h_range``: the textbook GCP layout."""
    rng = np.random.default_rng(seed)
    f = np.array([margin, 1 - margin])
    rows = np.repeat(f, 2) * shape[0]
    cols = np.tile(f, 2) * shape[1]
    h = rng.uniform(*h_range, 4)
    lon, lat = rpc.localize(rows, cols, h)
    return lon, lat, h


def synthetic_block(true: Sequence[RPC], biased: Sequence[RPC], tie, gcps=None, noise_px: float = 0.1,
                    sigma_px: float = 0.3, gcp_sigma_m: float = 0.01, use_dem: bool = False, seed: int = 0):
    """A :class:`~tiledsm.orient.adjust.Block` of tie points ``tie = (lon,
    lat, h)`` seen in every view and GCPs ``gcps = (lon, lat, h)`` (or
    None), measured with the ``true`` cameras plus Gaussian noise
    (``noise_px`` per axis); tie points start at their intersection with
    the ``biased`` cameras."""
    from tiledsm.orient.adjust import Block, intersect

    rng = np.random.default_rng(seed)
    v = len(true)
    groups = [("t", tie, False)] + ([("g", gcps, True)] if gcps is not None else [])
    img, pt, row, col, ground0, prior, ids = [], [], [], [], [], [], []
    n0 = 0
    for prefix, (lon, lat, h), is_gcp in groups:
        n = len(lon)
        p = project_all(true, lon, lat, h) + rng.normal(0, noise_px, (v, n, 2))
        img.append(np.repeat(np.arange(v), n))
        pt.append(n0 + np.tile(np.arange(n), v))
        row.append(p[:, :, 0].ravel())
        col.append(p[:, :, 1].ravel())
        if is_gcp:
            ground0.append(np.column_stack([lon, lat, h]))
            prior.append(np.full(n, gcp_sigma_m))
        else:
            g, _ = intersect(biased, img[-1], pt[-1] - n0, row[-1], col[-1], n)
            ground0.append(g)
            prior.append(np.full(n, np.inf))
        ids += [f"{prefix}{k}" for k in range(n)]
        n0 += n
    prior = np.concatenate(prior)
    return Block(np.concatenate(img), np.concatenate(pt), np.concatenate(row), np.concatenate(col),
                 np.full(sum(len(a) for a in img), sigma_px), np.vstack(ground0), prior,
                 np.isinf(prior) & use_dem, np.array(ids))
