"""Shifting kernel, Nuth & Kääb on analytic terrain (and against xdem), tiled == untiled."""

import warnings

import numpy as np
import pytest
from pydantic import ValidationError
from scipy import ndimage

from tiledsm.compare import CompareSpec, CoregFitSpec, align_dsms, fit_coregistration
from tiledsm.compare.coreg import COREG_METHODS, Coregistration, register_coreg, shift_array, shift_halo, shifted_at
from tiledsm.compare.stage import difference_lazy


def test_integer_shift_is_exact_and_moves_content_down_right():
    a = np.arange(48, dtype=np.float32).reshape(6, 8)
    out = shift_array(a, 2, 3)
    assert np.array_equal(out[2:, 3:], a[:-2, :-3])
    assert np.isnan(out[:2]).all() and np.isnan(out[:, :3]).all()


def test_linear_shift_matches_scipy_ndimage():
    rng = np.random.default_rng(0)
    a = ndimage.gaussian_filter(rng.normal(size=(40, 50)), 2).astype(np.float64)
    dy, dx = 1.37, -2.62
    got = shift_array(a, dy, dx, kernel="linear")
    ref = ndimage.shift(a, (dy, dx), order=1, mode="constant", cval=np.nan)
    inner = (slice(4, -4), slice(4, -4))
    assert np.allclose(got[inner], ref[inner], atol=1e-5)


def test_cubic_shift_reproduces_smooth_function():
    r, c = np.mgrid[0:40, 0:40].astype(float)
    f = lambda r, c: np.sin(r / 5.0) + np.cos(c / 7.0)  # noqa: E731
    got = shift_array(f(r, c), 0.3, -1.45)
    truth = f(r - 0.3, c + 1.45)
    assert np.nanmax(np.abs(got - truth)[3:-3, 3:-3]) < 2e-4
    assert shift_halo(0.3, -1.45) == 3


@pytest.mark.parametrize("kernel", ["cubic", "linear"])
@pytest.mark.parametrize("dy, dx", [(0.3, -1.45), (2.0, 3.0), (-1.6, 0.0)])
def test_shift_at_cells_is_the_whole_shift_at_those_cells(kernel, dy, dx):
    """The fit's iterations interpolate at their sample cells only: bit for
    bit the cells of the whole-array shift, NaN next to holes and edges."""
    rng = np.random.default_rng(1)
    a = rng.normal(300, 5, (37, 41)).astype(np.float32)
    a[10:13, 20:22] = np.nan
    index = np.sort(rng.choice(a.size, 600, replace=False))
    whole = shift_array(a, dy, dx, kernel).ravel()[index]
    got = shifted_at(a, index, dy, dx, kernel)
    assert got.dtype == np.float32 and np.array_equal(got, whole, equal_nan=True)
    assert np.isnan(got).any() and np.isfinite(got).any()


@pytest.mark.parametrize("max_samples", [0, 5_000])
def test_nuth_kaab_on_a_subsample_recovers_known_shift(synth, max_samples):
    """Iterations on an evenly strided subsample of 5 000 of the ~60 000
    candidate cells find the known shift as the full fit does (measured:
    within 0.002 px of it)."""
    shape = (250, 260)
    ref = synth.terrain(*synth.centres(shape))
    oth = synth.terrain(*synth.centres(shape, 1.6, 2.3)) + 1.25
    pair = align_dsms(synth.to_dataarray(ref, "ref"), synth.to_dataarray(oth, "other"), chunks=128)
    c = fit_coregistration(pair, CompareSpec(coreg_fit=CoregFitSpec(max_samples=max_samples)))
    assert c.dx_px == pytest.approx(2.3, abs=0.01) and c.dy_px == pytest.approx(1.6, abs=0.01)
    assert c.dz == pytest.approx(-1.25, abs=0.01) and c.converged


def test_registry_refuses_duplicates_and_lists_names():
    assert {"nuth_kaab", "none"} <= set(COREG_METHODS)
    with pytest.raises(ValueError, match="already registered"):
        register_coreg("nuth_kaab")(lambda w, p: Coregistration("x"))
    with pytest.raises(ValidationError, match="coreg\n.*unknown co-registration method 'bogus'.*nuth_kaab"):
        CompareSpec(coreg="bogus")


@pytest.mark.parametrize("drow, dcol", [(1.6, 2.3), (-3.25, 0.4)])
def test_nuth_kaab_recovers_known_shift(synth, drow, dcol):
    shape = (250, 260)
    ref = synth.terrain(*synth.centres(shape))
    oth = synth.terrain(*synth.centres(shape, drow, dcol)) + 1.25  # other[i,j] = ref(i+drow, j+dcol) + 1.25
    pair = align_dsms(synth.to_dataarray(ref, "ref"), synth.to_dataarray(oth, "other"), chunks=128)
    c = fit_coregistration(pair, CompareSpec())
    assert c.dx_px == pytest.approx(dcol, abs=0.01) and c.dy_px == pytest.approx(drow, abs=0.01)
    assert c.dz == pytest.approx(-1.25, abs=0.01)
    assert c.converged and c.nmad_after < 0.05 < c.nmad_before
    g = c.ground(pair.crs, pair.transform, synth.RES, -synth.RES)
    assert g["dx"] == pytest.approx(dcol * synth.RES, abs=0.1) and g["dy"] == pytest.approx(-drow * synth.RES, abs=0.1)


def test_deramp_removes_a_tilt(synth):
    shape = (200, 200)
    r, c = np.mgrid[0 : shape[0], 0 : shape[1]]
    ref = synth.terrain(*synth.centres(shape))
    oth = synth.terrain(*synth.centres(shape, 0.5, -0.7)) + 0.002 * c - 0.003 * r + 0.4
    pair = align_dsms(synth.to_dataarray(ref, "ref"), synth.to_dataarray(oth, "other"), chunks=64)
    co = fit_coregistration(pair, CompareSpec(deramp=True))
    # shift and tilt are slightly correlated on a 2 km window of long-wavelength terrain
    assert co.ramp_col == pytest.approx(-0.002, abs=1.5e-4) and co.ramp_row == pytest.approx(0.003, abs=1.5e-4)
    assert co.dx_px == pytest.approx(-0.7, abs=0.02) and co.dy_px == pytest.approx(0.5, abs=0.02)
    dh = difference_lazy(pair, co).compute()
    assert np.nanmax(np.abs(dh[5:-5, 5:-5])) < 0.05


def test_xdem_nuthkaab_agrees(synth, tmp_path):
    xdem = pytest.importorskip("xdem")
    shape = (300, 300)
    drow, dcol = 1.6, 2.3
    ref = synth.terrain(*synth.centres(shape))
    oth = synth.terrain(*synth.centres(shape, drow, dcol))
    rp = synth.write_tif(tmp_path / "r.tif", ref)
    op = synth.write_tif(tmp_path / "o.tif", oth)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        nk = xdem.coreg.NuthKaab()
        nk.fit(xdem.DEM(str(rp)), xdem.DEM(str(op)))
    out = nk.meta["outputs"]["affine"]
    # xdem's shift_x/shift_y (georeferenced units) are the translation applied to the
    # DEM to align, as ours: dx_px = shift_x / a, dy_px = shift_y / e
    x_dx, x_dy = out["shift_x"] / synth.RES, out["shift_y"] / -synth.RES
    pair = align_dsms(synth.to_dataarray(ref, "ref"), synth.to_dataarray(oth, "other"), chunks=150)
    c = fit_coregistration(pair, CompareSpec())
    assert abs(c.dx_px - x_dx) < 0.1 and abs(c.dy_px - x_dy) < 0.1
    assert abs(x_dx - dcol) < 0.1 and abs(x_dy - drow) < 0.1  # xdem itself finds the truth here


@pytest.mark.parametrize("chunks", [17, 64, 1000])
def test_tiled_difference_equals_untiled(synth, chunks):
    shape = (150, 170)
    ref = synth.terrain(*synth.centres(shape))
    oth = synth.terrain(*synth.centres(shape, -2.4, 1.7))
    oth[40:60, 30:90] = np.nan
    co = Coregistration("given", dx_px=1.7, dy_px=-2.4, dz=0.3, ramp_col=1e-3, ramp_row=-2e-3, ramp_origin=(75, 85))
    pair = align_dsms(synth.to_dataarray(ref, "ref"), synth.to_dataarray(oth, "other"), chunks=chunks)
    tiled = difference_lazy(pair, co).compute()
    r, c = np.mgrid[0 : shape[0], 0 : shape[1]]
    untiled = (shift_array(oth.astype(np.float32), -2.4, 1.7) + co.vertical_field(r, c)).astype(np.float32) - ref.astype(np.float32)
    assert np.array_equal(np.isnan(tiled), np.isnan(untiled))
    assert np.array_equal(tiled[np.isfinite(tiled)], untiled.astype(np.float32)[np.isfinite(untiled)])
    assert np.nanmax(np.abs(tiled - 0.3 - (1e-3 * (c - 85) - 2e-3 * (r - 75)))) < 0.01  # correct alignment
