"""RPC derived models: scaled, cropped, with_affine (exact cases)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import require_shared
from tiledsm.geometry.fit import with_affine
from tiledsm.geometry import RPC
from tiledsm.geometry.rpc import rpc_terms


@pytest.fixture(scope="module")
def img01():
    path = require_shared("s2p_pair", "input_pair", "img_01.tif")
    import rasterio

    with rasterio.open(path) as ds:
        return RPC.from_gdal(ds.rpcs.to_dict(), source=str(path)), ds.shape


def _ground(rpc, shape, n=500, seed=0):
    rng = np.random.default_rng(seed)
    h = rng.uniform(2000, 2600, n)
    lon, lat = rpc.localize(rng.uniform(0, shape[0], n), rng.uniform(0, shape[1], n), h)
    return lon, lat, h


def test_compiled_projection_matches_the_monomial_form(img01):
    """``project``'s compiled loop against the ratio of the four
    polynomials over the stacked monomials (:func:`rpc_terms`), on the
    image and its surroundings, scalars and 2-D arrays alike: the sums'
    order differs, so they agree to rounding (measured: 1.8e-11 px at
    most on these points)."""
    rpc, shape = img01
    lon, lat, h = _ground(rpc, shape)
    lon = np.concatenate([lon, lon + 0.3 * rpc.lon_scale])  # beyond the image too
    lat, h = np.concatenate([lat, lat]), np.concatenate([h, h - 300])
    t = rpc_terms(*rpc._normalise_ground(lon, lat, h))
    ln = (rpc.line_num @ t) / (rpc.line_den @ t)
    sn = (rpc.samp_num @ t) / (rpc.samp_den @ t)
    row, col = rpc.project(lon, lat, h)
    np.testing.assert_allclose(row, ln * rpc.line_scale + rpc.line_off + 0.5, rtol=0, atol=3e-11)
    np.testing.assert_allclose(col, sn * rpc.samp_scale + rpc.samp_off + 0.5, rtol=0, atol=3e-11)
    r2, c2 = rpc.project(lon.reshape(40, 25), lat.reshape(40, 25), h.reshape(40, 25))
    assert r2.shape == (40, 25) and np.array_equal(r2.ravel(), row) and np.array_equal(c2.ravel(), col)
    r0, c0 = rpc.project(lon[0], lat[0], h[0])
    assert np.ndim(r0) == 0 and (r0, c0) == (row[0], col[0])


@pytest.mark.parametrize("s", [2.0, 0.5, 3.0, 1 / 3])
def test_scaled_is_exact(img01, s):
    rpc, shape = img01
    lon, lat, h = _ground(rpc, shape)
    r, c = rpc.project(lon, lat, h)
    rs, cs = rpc.scaled(s).project(lon, lat, h)
    np.testing.assert_allclose(rs, s * r, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cs, s * c, rtol=0, atol=1e-9)


def test_scaled_corner_convention(img01):
    """Pixel [0, 0] of a 2x image covers the top-left quarter of old pixel [0, 0]:
    its centre (0.5, 0.5) is old (0.25, 0.25)."""
    rpc, _ = img01
    lon, lat = rpc.localize(0.25, 0.25, 2300.0)
    r, c = rpc.scaled(2).project(lon, lat, 2300.0)
    assert r == pytest.approx(0.5, abs=1e-9) and c == pytest.approx(0.5, abs=1e-9)


def test_cropped_is_exact(img01):
    rpc, shape = img01
    lon, lat, h = _ground(rpc, shape)
    r, c = rpc.project(lon, lat, h)
    rc, cc = rpc.cropped(100, 250.5).project(lon, lat, h)
    np.testing.assert_allclose(rc, r - 100, atol=1e-9)
    np.testing.assert_allclose(cc, c - 250.5, atol=1e-9)


def test_crop_then_scale_matches_gdal_window(img01, tmp_path):
    """Against GDAL: the cropped/scaled RPC written to a GeoTIFF and read by
    rasterio's RPCTransformer gives our predicted pixel positions."""
    from rasterio.transform import RPCTransformer

    rpc, shape = img01
    new = rpc.cropped(10, 20).scaled(2.0)
    lon, lat, h = _ground(rpc, shape, n=50)
    r, c = rpc.project(lon, lat, h)
    with RPCTransformer(new.to_gdal()) as tr:
        gr, gc = tr.rowcol(lon, lat, zs=h, op=lambda x: x)
    np.testing.assert_allclose(np.asarray(gr), 2 * (r - 10), atol=1e-3)
    np.testing.assert_allclose(np.asarray(gc), 2 * (c - 20), atol=1e-3)


def test_with_affine_exact_shift_and_scale(img01):
    """Fraser & Hanley: l + A0 + A1 l + A2 s = r, s + B0 + B1 l + B2 s = c;
    with A2 = B1 = 0 only offsets and scales change."""
    rpc, shape = img01
    a, b = (3.2, 1e-4, 0.0), (-7.5, 0.0, -2e-4)
    fixed = with_affine(rpc, a, b)
    lon, lat, h = _ground(rpc, shape)
    r, c = rpc.project(lon, lat, h)
    l, s = fixed.project(lon, lat, h)
    np.testing.assert_allclose(l + a[0] + a[1] * l + a[2] * s, r, atol=1e-9)
    np.testing.assert_allclose(s + b[0] + b[1] * l + b[2] * s, c, atol=1e-9)
    # the exact path keeps the coefficients
    np.testing.assert_array_equal(fixed.line_num, rpc.line_num)


def test_with_affine_projects_gcps_onto_measured_positions(img01):
    """Regression (issue 10: A1/A2 swapped, sign reversed): a biased RPC,
    A0..B2 estimated from 6 GCPs by the model's own linear equations, folded
    back: the corrected RPC lands on the measured GCP positions."""
    rpc, shape = img01
    truth = rpc
    lon, lat, h = _ground(rpc, shape, n=6, seed=3)
    l, s = truth.project(lon, lat, h)  # measured GCP positions
    biased = with_affine(truth, (-2.5, -1.5e-4, 2e-4), (4.0, 1e-4, 3e-4), image_shape=shape, h_range=(2000, 2600))
    r, c = biased.project(lon, lat, h)
    assert np.max(np.hypot(r - l, c - s)) > 2.0  # the bias is real
    design = np.column_stack([np.ones_like(l), l, s])
    a = np.linalg.lstsq(design, r - l, rcond=None)[0]
    b = np.linalg.lstsq(design, c - s, rcond=None)[0]
    fixed = with_affine(biased, a, b, image_shape=shape, h_range=(2000, 2600))
    lf, sf = fixed.project(lon, lat, h)
    assert np.max(np.hypot(lf - l, sf - s)) < 0.02
    # and the correction reproduces the true camera away from the GCPs
    lon2, lat2, h2 = _ground(rpc, shape, n=200, seed=4)
    lt, st = truth.project(lon2, lat2, h2)
    lf2, sf2 = fixed.project(lon2, lat2, h2)
    assert np.max(np.hypot(lf2 - lt, sf2 - st)) < 0.02


def test_with_affine_identity_roundtrip(img01):
    rpc, _ = img01
    assert with_affine(rpc, (0, 0, 0), (0, 0, 0)) == rpc


def test_projection_where_a_denominator_vanishes_is_not_finite():
    """A point where the line denominator is zero (normalised height 1 for
    ``1 - H``): the projection is not finite, as numpy's division gives,
    instead of the compiled loop raising ZeroDivisionError."""
    num = np.zeros(20)
    num[1] = 1.0  # L
    den = np.zeros(20)
    den[0], den[3] = 1.0, -1.0  # 1 - H
    one = np.zeros(20)
    one[0] = 1.0
    rpc = RPC(line_off=500, samp_off=500, lat_off=45, lon_off=5, height_off=100, line_scale=500, samp_scale=500,
              lat_scale=0.1, lon_scale=0.1, height_scale=50, line_num=num, line_den=den, samp_num=num, samp_den=one)
    row, col = rpc.project(np.array([5.01, 5.01]), np.array([45.0, 45.0]), np.array([150.0, 120.0]))
    assert not np.isfinite(row[0]) and np.isfinite(col[0])
    assert np.isfinite(row[1]) and row[1] == pytest.approx(500 + 0.5 + 500 * 0.1 / (1 - 0.4))
