"""Slope/aspect against analytic planes, metric steps against pyproj, statistics against numpy."""

import numpy as np
import pytest
from affine import Affine
from pyproj import Geod
from rasterio.crs import CRS

from tiledsm.compare.stats import HistogramStats, difference_statistics
from tiledsm.compare.terrain import metric_steps, slope_aspect, slope_percent


@pytest.mark.parametrize("gx, gy, aspect_deg", [(-0.2, 0.0, 90.0), (0.0, 0.3, 180.0), (0.1, 0.1, 225.0), (0.0, -0.5, 0.0)])
def test_slope_aspect_of_planes(gx, gy, aspect_deg):
    # plane z = gx * east + gy * north on a north-up 5 m grid (rows go south)
    r, c = np.mgrid[0:20, 0:30]
    east, north = 5.0 * c, -5.0 * r
    z = gx * east + gy * north
    slope, aspect = slope_aspect(z, 5.0, -5.0)
    inner = (slice(1, -1), slice(1, -1))
    assert np.allclose(slope[inner], np.degrees(np.arctan(np.hypot(gx, gy))), atol=1e-9)
    assert np.allclose(np.degrees(aspect[inner]) % 360, aspect_deg, atol=1e-9)
    assert np.allclose(slope_percent(z, 5.0, -5.0)[inner], 100 * np.hypot(gx, gy))
    assert np.isnan(slope[0]).all() and np.isnan(slope[:, -1]).all()


def test_metric_steps_geographic_match_geodesic_distances():
    t = Affine(1 / 1200, 0, 40.0, 0, -1 / 1200, 40.0)
    lat = np.array([40.0, 10.0, -60.0])
    sx, sy = metric_steps(CRS.from_epsg(4326), t, lat)
    g = Geod(ellps="WGS84")
    for k, phi in enumerate(lat):
        _, _, dxm = g.inv(40.0, phi, 40.0 + t.a, phi)
        _, _, dym = g.inv(40.0, phi - t.a / 2, 40.0, phi + t.a / 2)
        assert sx[k, 0] == pytest.approx(dxm, rel=1e-6)
        assert -sy[k, 0] == pytest.approx(dym, rel=1e-5)
    sx, sy = metric_steps(CRS.from_epsg(32632), Affine(2, 0, 0, 0, -2, 0), lat)
    assert np.all(sx == 2) and np.all(sy == -2)


def test_difference_statistics_against_numpy():
    rng = np.random.default_rng(1)
    v = rng.normal(0.3, 2.0, 10001)
    ref = rng.uniform(100, 200, v.size)
    v[::10] = np.nan
    s = difference_statistics(v, reference=ref)
    f = v[np.isfinite(v)]
    assert s["count"] == f.size and s["completeness"] == pytest.approx(f.size / v.size)
    assert s["mean"] == pytest.approx(f.mean()) and s["std"] == pytest.approx(f.std())
    assert s["rmse"] == pytest.approx(np.sqrt((f**2).mean()))
    assert s["median"] == pytest.approx(np.median(f))
    assert s["nmad"] == pytest.approx(1.4826 * np.median(np.abs(f - np.median(f))))
    assert s["mre"] == pytest.approx(np.mean(np.abs(f) / ref[np.isfinite(v)]))
    assert s["nmad"] == pytest.approx(2.0, rel=0.05)  # NMAD of a normal = sigma


def test_histogram_stats_match_exact_statistics_in_blocks():
    rng = np.random.default_rng(2)
    dh = rng.standard_t(3, size=(200, 300)) * 0.7 + 0.2
    ref = rng.uniform(50, 60, dh.shape)
    dh[rng.random(dh.shape) < 0.05] = np.nan
    grp = dh > 0.5
    hs = HistogramStats(("all", "pos"), -30.0, 30.0, 60000)
    parts = []
    for r0 in range(0, 200, 64):
        for c0 in range(0, 300, 100):
            s = (slice(r0, r0 + 64), slice(c0, c0 + 100))
            members = np.stack([np.ones_like(grp[s]), grp[s]])
            parts.append(hs.block(dh[s], ref[s], members, np.ones((2,) + dh[s].shape, bool)))
    part = parts[0]
    for p in parts[1:]:
        part = HistogramStats.merge(part, p)
    got = hs.finalize(part)
    for name, sel in (("all", np.ones_like(grp)), ("pos", grp)):
        exact = difference_statistics(dh[sel], reference=ref[sel])
        for key in ("count", "mean", "std", "rmse", "mae", "mre", "min", "max"):
            assert got[name][key] == pytest.approx(exact[key], rel=1e-9, abs=1e-12), key
        width = 60.0 / 60000
        assert abs(got[name]["median"] - exact["median"]) <= width
        assert abs(got[name]["nmad"] - exact["nmad"]) <= 1.4826 * 2 * width


@pytest.mark.parametrize("chunks", [(150, 170), (64, 64), (37, 101), (150, 1)])
def test_lazy_histogram_stats_equal_numpy_oracle_in_any_chunking(chunks):
    """``HistogramStats.lazy_total`` (blockwise partials + ``da.reduction``) against numpy on the whole array."""
    import dask.array as da

    rng = np.random.default_rng(5)
    dh = (rng.standard_t(3, size=(150, 170)) * 0.7 + 0.2).astype(np.float32)
    ref = rng.uniform(50, 60, dh.shape).astype(np.float32)
    dh[rng.random(dh.shape) < 0.05] = np.nan
    ref[rng.random(dh.shape) < 0.02] = np.nan
    ref[3, :5] = 0.0  # |dh| / 0 is not a relative error: left out of MRE like numpy's non-finite ratios
    hs = HistogramStats(("all", "pos", "none"), -30.0, 30.0, 60000)

    def block(d, r):
        members = np.stack([np.ones(d.shape, bool), d > 0.5, np.zeros(d.shape, bool)])
        return hs.block_packed(d, r, members, np.broadcast_to(np.isfinite(r), members.shape))

    lazy = hs.lazy_total(block, da.from_array(dh, chunks=chunks), da.from_array(ref, chunks=chunks))
    total = lazy.compute(scheduler="synchronous")
    assert total.shape == (3, hs.width)
    got = hs.finalize(total)
    width = 60.0 / 60000
    for name, sel in (("all", np.ones(dh.shape, bool)), ("pos", dh > 0.5)):
        v = dh[sel].astype(np.float64)
        r = ref[sel].astype(np.float64)
        v = v[np.isfinite(v)]
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.abs(dh[sel].astype(np.float64)) / np.abs(r)
        rel = rel[np.isfinite(rel)]
        med = np.median(v)
        assert got[name]["count"] == v.size
        assert got[name]["cells"] == int(np.isfinite(ref).sum())
        assert got[name]["mean"] == pytest.approx(v.mean(), rel=1e-12)
        assert got[name]["std"] == pytest.approx(v.std(), rel=1e-9)
        assert got[name]["rmse"] == pytest.approx(np.sqrt(np.mean(v * v)), rel=1e-12)
        assert got[name]["mae"] == pytest.approx(np.abs(v).mean(), rel=1e-12)
        assert got[name]["mre"] == pytest.approx(rel.mean(), rel=1e-12)
        assert (got[name]["min"], got[name]["max"]) == (v.min(), v.max())
        assert abs(got[name]["median"] - med) <= width
        assert abs(got[name]["nmad"] - 1.4826 * np.median(np.abs(v - med))) <= 1.4826 * 2 * width
    assert got["none"]["count"] == 0 and np.isnan(got["none"]["median"])
    # the histogram (median/NMAD) does not depend on the chunking at all
    whole = hs.lazy_total(block, da.from_array(dh), da.from_array(ref)).compute(scheduler="synchronous")
    assert np.array_equal(total[:, : hs.bins + 2], whole[:, : hs.bins + 2])
