"""Physical pushbroom camera: inverse, parallax, GSD, RPC fit."""

from __future__ import annotations

import math

import numpy as np

from tiledsm.geometry.pushbroom import PushbroomCamera

E0, N0 = 650000.0, 4896000.0


def _cam(**kw):
    base = dict(crs="EPSG:32631", e0=E0, n0=N0, h0=300.0, rows=2000, cols=3000, gsd=0.5)
    base.update(kw)
    return PushbroomCamera(**base)


def test_project_localize_round_trip():
    cam = _cam(pitch_deg=-15.0, roll_deg=4.0, azimuth_deg=197.0)
    rng = np.random.default_rng(0)
    r = rng.uniform(0, 2000, 500)
    c = rng.uniform(0, 3000, 500)
    h = rng.uniform(100, 800, 500)
    x, y = cam.localize_xy(r, c, h)
    r2, c2 = cam.project_xy(x, y, h)
    assert np.abs(r2 - r).max() < 1e-7 and np.abs(c2 - c).max() < 1e-7
    lon, lat = cam.localize(r, c, h)
    r3, c3 = cam.project(lon, lat, h)
    assert np.abs(r3 - r).max() < 1e-6 and np.abs(c3 - c).max() < 1e-6


def test_aim_point_gsd_and_line_by_line_acquisition():
    cam = _cam(pitch_deg=10.0, roll_deg=2.0)
    r, c = cam.project_xy(E0, N0, 300.0)
    assert abs(r - 1000.0) < 1e-9 and abs(c - 1500.0) < 1e-9
    # one row = one gsd along track; one column = one gsd across at the centre
    x, y = cam.localize_xy(np.array([1000.0, 1001.0, 1000.0, 1000.0]), np.array([1500.0, 1500.0, 1499.5, 1500.5]), 300.0)
    assert abs(math.hypot(x[1] - x[0], y[1] - y[0]) - 0.5) < 1e-9
    assert abs(math.hypot(x[3] - x[2], y[3] - y[2]) - 0.5) < 1e-9
    # each row has its own sensor position: successive rows are 1 gsd apart along the orbit
    o, _ = cam.rays(np.array([0.5, 1.5]), np.array([0.0, 0.0]))
    assert abs(np.linalg.norm(o[1] - o[0]) - 0.5) < 1e-9 and abs(o[0, 2] - o[1, 2]) < 1e-9
    assert abs(o[0, 2] - (300.0 + 700e3)) < 1e-6


def test_parallax_gives_the_base_to_height_ratio():
    t = 0.3
    a = _cam(pitch_deg=math.degrees(math.atan(-t)))
    b = _cam(pitch_deg=math.degrees(math.atan(t)))
    assert abs(np.linalg.norm(a.parallax() - b.parallax()) - 2 * t) < 1e-12
    # measured: a point raised by dh moves by tan(pitch) * dh along track in ground units
    x, y = a.localize_xy(1000.0, 1500.0, np.array([300.0, 310.0]))
    assert abs(math.hypot(x[1] - x[0], y[1] - y[0]) - 10 * t) < 1e-9


def test_fitted_rpc_reproduces_the_pushbroom():
    from tiledsm.geometry.fit import fit_rpc

    cam = _cam(pitch_deg=-12.0, roll_deg=3.0, azimuth_deg=192.0)
    r = np.array([0, 0, 2000, 2000] * 2, float)
    c = np.array([0, 3000, 0, 3000] * 2, float)
    h = np.repeat([0.0, 900.0], 4)
    lon, lat = cam.localize(r, c, h)
    rpc = fit_rpc(cam.project, (lon.min(), lon.max()), (lat.min(), lat.max()), (0.0, 900.0), (2000, 3000))
    rng = np.random.default_rng(1)
    rr = rng.uniform(0, 2000, 2000)
    cc = rng.uniform(0, 3000, 2000)
    hh = rng.uniform(0, 900, 2000)
    plon, plat = cam.localize(rr, cc, hh)
    fr, fc = rpc.project(plon, plat, hh)
    assert np.hypot(fr - rr, fc - cc).max() < 0.05
