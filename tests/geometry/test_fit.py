"""fit_rpc: refit of real RPCs, affine-corrected RPCs and an analytic pushbroom."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import require_shared
from tiledsm.geometry.fit import with_affine
from tiledsm.errors import RPCError
from tiledsm.geometry import RPC, fit_rpc, fit_rpc_report


A_WGS84 = 6378137.0
E2_WGS84 = 6.69437999014e-3


def _ecef(lon, lat, h):
    lon, lat = np.radians(lon), np.radians(lat)
    n = A_WGS84 / np.sqrt(1 - E2_WGS84 * np.sin(lat) ** 2)
    return np.stack([(n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
                     (n * (1 - E2_WGS84) + h) * np.sin(lat)])


class Pushbroom:
    """Tiny analytic linear-array camera (independent of tiledsm).

    Straight-line orbit flying north at ``altitude`` over (lon0, lat0) on the
    WGS84 ellipsoid (ECEF); one line per ``gsd / speed`` s; attitude =
    constant roll/pitch + a pitch drift + sinusoidal roll and pitch jitter;
    cubic distortion along the array (``distortion`` px at its ends). ``row`` solves "the point lies
    in the sensor plane at time t" by Newton; ``col`` is the central
    projection inside that plane. GDAL convention (row = t / line_time).
    """

    def __init__(self, lon0, lat0, shape, *, gsd=0.5, altitude=695e3, roll=8.0, pitch=12.0,
                 drift=0.05, jitter=2e-5, jitter_hz=3.0, distortion=2.0, speed=7000.0):
        self.shape = shape
        g = _ecef(lon0, lat0, 0.0)
        up = g - _ecef(lon0, lat0, -1.0)
        north = _ecef(lon0, lat0 + 1e-4, 0.0) - g
        north -= up * (north @ up)
        north /= np.linalg.norm(north)
        self.up, self.north, self.east = up, north, np.cross(north, up)
        self.v = north * speed
        self.line_time = gsd / speed
        self.t_mid = shape[0] / 2 * self.line_time
        self.s_mid = g + altitude * (up - np.tan(np.radians(pitch)) * north - np.tan(np.radians(roll)) * self.east)
        self.roll, self.pitch = np.radians(roll), np.radians(pitch)
        self.drift, self.jitter, self.w = np.radians(drift), jitter, 2 * np.pi * jitter_hz
        self.f_px = altitude / np.cos(self.roll) / np.cos(self.pitch) / gsd
        self.k = distortion

    def _axes(self, t):
        dt = t - self.t_mid
        p = self.pitch + self.drift * dt + self.jitter * np.sin(self.w * dt)
        r = self.roll + self.jitter * np.cos(1.3 * self.w * dt)
        # boresight tilted forward (north) by p and sideways (east) by r
        b = (-self.up[:, None] + np.tan(p) * self.north[:, None] + np.tan(r) * self.east[:, None])
        b /= np.linalg.norm(b, axis=0)
        u = np.cross(b.T, self.north).T  # across-track axis in the sensor plane
        u /= np.linalg.norm(u, axis=0)
        return b, u, np.cross(u.T, b.T).T  # boresight, array axis, plane normal

    def _plane(self, x, t):
        _, _, n = self._axes(t)
        return np.sum((x - self.s_mid[:, None] - self.v[:, None] * (t - self.t_mid)) * n, axis=0)

    def project(self, lon, lat, h):
        lon, lat, h = np.broadcast_arrays(*(np.asarray(a, float) for a in (lon, lat, h)))
        x = _ecef(lon.ravel(), lat.ravel(), h.ravel())
        t = np.full(x.shape[1], self.t_mid)
        for _ in range(30):
            g = self._plane(x, t)
            step = g * 1e-3 / (self._plane(x, t + 1e-3) - g)
            t = t - step
            if np.max(np.abs(step)) < 1e-13:
                break
        b, u, _ = self._axes(t)
        d = x - self.s_mid[:, None] - self.v[:, None] * (t - self.t_mid)
        xf = np.sum(d * u, axis=0) / np.sum(d * b, axis=0) * self.f_px
        half = self.shape[1] / 2
        col = xf + self.k * (xf / half) ** 3 + half
        return (t / self.line_time).reshape(lon.shape), col.reshape(lon.shape)


@pytest.fixture(scope="module")
def img01():
    path = require_shared("s2p_pair", "input_pair", "img_01.tif")
    import rasterio

    with rasterio.open(path) as ds:
        return RPC.from_gdal(ds.rpcs.to_dict(), source=str(path)), ds.shape


def _random_points(rpc, shape, h_range, n=2000, seed=0):
    """Ground points seen inside the image, at random heights."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(0, shape[0], n)
    c = rng.uniform(0, shape[1], n)
    h = rng.uniform(*h_range, n)
    lon, lat = rpc.localize(r, c, h)
    return lon, lat, h


def test_refit_real_rpc_within_0_01_px(img01):
    rpc, shape = img01
    h = (2000.0, 2600.0)
    lon_r, lat_r = rpc.ground_box((0, shape[0], 0, shape[1]), h)
    fit, rep = fit_rpc_report(rpc.project, lon_r, lat_r, h, shape)
    assert rep.n_check == 20 * 20 * 8
    assert rep.check_max_px < 0.01
    lon, lat, hh = _random_points(rpc, shape, h)
    r0, c0 = rpc.project(lon, lat, hh)
    r1, c1 = fit.project(lon, lat, hh)
    assert np.max(np.hypot(r1 - r0, c1 - c0)) < 0.01
    # normalisation follows the image: centre row/col at the image centre
    assert fit.line_off == pytest.approx(shape[0] / 2 - 0.5)
    assert fit.samp_scale == pytest.approx(shape[1] / 2)


def test_affine_bias_folded_into_rpc(img01):
    rpc, shape = img01
    a = (2.7, 3e-4, -2e-4)
    b = (-1.4, 1.5e-4, 4e-4)
    h = (2000.0, 2600.0)
    fixed = with_affine(rpc, a, b, image_shape=shape, h_range=h)
    lon, lat, hh = _random_points(rpc, shape, h, seed=1)
    r, c = rpc.project(lon, lat, hh)
    got_l, got_s = fixed.project(lon, lat, hh)
    # l + A0 + A1 l + A2 s = r and s + B0 + B1 l + B2 s = c (Fraser & Hanley 2003)
    back_r = got_l + a[0] + a[1] * got_l + a[2] * got_s
    back_c = got_s + b[0] + b[1] * got_l + b[2] * got_s
    assert np.max(np.hypot(back_r - r, back_c - c)) < 0.01
    # the bias is not negligible: the uncorrected RPC is pixels away
    assert np.max(np.hypot(r - got_l, c - got_s)) > 1.0


def test_pushbroom_fitted_within_0_05_px():
    shape = (6000, 5000)
    cam = Pushbroom(5.2, 44.2, shape, jitter=0.0, drift=0.05, distortion=3.0)
    # the camera's own centre is the image centre (sanity of the test camera)
    r, c = cam.project(5.2, 44.2, 0.0)
    assert abs(r - shape[0] / 2) < 1e-6 and abs(c - shape[1] / 2) < 1e-6
    half_lat = shape[0] * 0.5 * 0.5 / 111e3
    half_lon = shape[1] * 0.5 * 0.5 / 111e3 / np.cos(np.radians(44.2))
    box = ((5.2 - half_lon, 5.2 + half_lon), (44.2 - half_lat, 44.2 + half_lat), (-200.0, 1800.0))
    fit, rep = fit_rpc_report(cam.project, *box, shape)
    assert rep.check_max_px < 0.05
    rng = np.random.default_rng(2)
    lon = rng.uniform(*box[0], 3000)
    lat = rng.uniform(*box[1], 3000)
    h = rng.uniform(*box[2], 3000)
    r0, c0 = cam.project(lon, lat, h)
    r1, c1 = fit.project(lon, lat, h)
    assert np.max(np.hypot(r1 - r0, c1 - c0)) < 0.05


def test_held_out_check_catches_unmodellable_camera():
    """Strong attitude jitter (tens of px at 3 Hz) cannot be an RPC: refused."""
    shape = (4000, 4000)
    cam = Pushbroom(5.2, 44.2, shape, jitter=2e-5)
    half = shape[0] * 0.5 * 0.5 / 111e3
    box = ((5.2 - half / np.cos(np.radians(44.2)), 5.2 + half / np.cos(np.radians(44.2))),
           (44.2 - half, 44.2 + half), (-100.0, 1500.0))
    with pytest.raises(RPCError, match="held-out error"):
        fit_rpc(cam.project, *box, shape, max_error=0.05)


def test_nan_projections_are_dropped(img01):
    rpc, shape = img01
    h = (2000.0, 2600.0)
    lon_r, lat_r = rpc.ground_box((0, shape[0], 0, shape[1]), h)
    mid = 0.5 * (lon_r[0] + lon_r[1])

    def half_blind(lon, lat, hh):
        r, c = rpc.project(lon, lat, hh)
        return np.where(lon < mid, np.nan, r), c

    fit, rep = fit_rpc_report(half_blind, lon_r, lat_r, h, shape)
    assert rep.n_fit < 21 * 21 * 9
    assert np.isfinite(fit.line_num).all()


def test_bad_ranges_rejected():
    with pytest.raises(ValueError, match="lon_range"):
        fit_rpc(lambda *a: (a[0], a[1]), (1.0, 1.0), (0.0, 1.0), (0.0, 1.0), (10, 10))
