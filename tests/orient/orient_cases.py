"""Shared cases of the orientation tests (constants and helpers; the
fixtures in conftest.py use them). A uniquely named module, imported as
``from orient_cases import ...``: ``conftest`` is not importable by name
when several test folders have one."""

from __future__ import annotations

import numpy as np

SIZE = 1024
H_RANGE = (200.0, 400.0)
#: injected (A, B) per view: 3 px shifts, 1e-4 scale/shear
BIASES = (
    ((3.0, 1e-4, -1e-4), (-2.0, 1e-4, 1e-4)),
    ((-3.0, -1e-4, 1e-4), (3.0, 1e-4, -1e-4)),
    ((2.0, 1e-4, 1e-4), (2.0, -1e-4, 1e-4)),
)


def relative_error(rpcs, true, lon, lat, h) -> float:
    """RMS reprojection residual (px) of the *true* correspondences of
    ground points intersected with ``rpcs``: 0 when the cameras agree with
    each other (whatever their common absolute error)."""
    from tiledsm.orient.adjust import intersect
    from simulate import project_all

    p = project_all(true, lon, lat, h)
    v, n = p.shape[:2]
    img = np.repeat(np.arange(v), n)
    pt = np.tile(np.arange(n), v)
    _, res = intersect(rpcs, img, pt, p[:, :, 0].ravel(), p[:, :, 1].ravel(), n)
    return float(np.sqrt(np.mean(np.sum(res**2, axis=1))))


def write_gcp_files(true, names, folder):
    """``gcps.csv`` (4 corner points, 0.05 px noise) and ``checks.csv`` (20
    random points) of a 512-px scene seen by the ``true`` cameras, in
    ``folder``; returns both paths."""
    from simulate import corner_points, ground_points, write_points_csv

    gl, ga, gh = corner_points(true[0], (512, 512), (300, 400), seed=1)
    write_points_csv(folder / "gcps.csv", names, true, gl, ga, gh, noise_px=0.05, shape=(512, 512))
    cl, ca, ch = ground_points(true[0], (512, 512), (300, 400), 20, seed=2)
    write_points_csv(folder / "checks.csv", names, true, cl, ca, ch, prefix="c", shape=(512, 512))
    return folder / "gcps.csv", folder / "checks.csv"
