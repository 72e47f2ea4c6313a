"""Orthorectification: synthetic truth (texture, visibility), tile
invariance, a frame camera on an analytic texture, bad inputs."""

import numpy as np
import pytest
from pydantic import ValidationError
import xarray as xr
from skimage.registration import phase_cross_correlation

from tiledsm.io.grids import grid_array
from tiledsm.errors import GridError, InvalidOptionError, NoOverlapError
from tiledsm.geometry.frame import FrameCamera, rotation_nadir
from tiledsm.geometry.grid import GroundGrid
from tiledsm.ortho.recipe import OrthoSpec
from tiledsm.ortho.rectify import ImageSource, orthorectify
from tiledsm.ortho.stage import resolution_factor


def _raster(path):
    return xr.open_dataarray(path, engine="rasterio").squeeze("band", drop=True)


def _truth_dn(scene):
    """Noise- and blur-free DN of the truth surface at the truth grid's cell centres."""
    from tiledsm.synth.render import RadiometryParams, surface_lattice

    g, rp = scene.grid, RadiometryParams()
    xs, ys = g.x - scene.origin[0], g.y - scene.origin[1]
    step = g.resolution / 2
    x0, y0, _, rad = surface_lattice(scene.world, xs.min(), xs.max(), ys.min(), ys.max(), step, rp)
    j = np.rint((xs - x0) / step).astype(int)
    i = np.rint((ys - y0) / step).astype(int)
    return rp.offset + rp.gain * rad[np.ix_(i, j)]


@pytest.fixture(scope="module")
def orthos(ortho_scene):
    dsm = _raster(ortho_scene.truth_dsm).chunk(64)
    return [orthorectify(ImageSource.from_file(v), dsm, OrthoSpec(kernel="cs"), chunk=64).values
            for v in ortho_scene.views]


def test_ortho_matches_truth_texture(ortho_scene, orthos):
    truth = _truth_dn(ortho_scene)
    vis = _raster(ortho_scene.visible_mask).values.astype(bool)
    for o in orthos:
        m = vis & np.isfinite(o)
        assert m.mean() > 0.6
        # the views have a 0.5 px Gaussian PSF and 3 DN noise: correlation, not equality
        assert np.corrcoef(o[m], truth[m])[0, 1] > 0.988  # measured 0.9905, 0.9908
        assert abs(np.mean(o[m] - truth[m])) < 2.0  # DN, measured -0.08, -0.25
        a = np.where(np.isfinite(o), o, np.nanmean(o))[32:224, 32:224]
        shift, _, _ = phase_cross_correlation(truth[32:224, 32:224], a, upsample_factor=100)
        assert np.abs(shift).max() <= 0.1  # px, measured 0.04, 0.08


def test_hidden_cells_are_the_invisible_ones(ortho_scene, orthos):
    for o, vpath in zip(orthos, ortho_scene.visible_views):
        vis = _raster(vpath).values.astype(bool)
        hid = np.isnan(o)
        assert (~vis).mean() > 0.05  # the scene has occlusions to find
        assert hid[~vis].mean() > 0.95  # measured 0.969, 0.985
        assert hid[vis].mean() < 1e-3  # measured 8e-5, 2e-5


@pytest.mark.parametrize("kernel,factor", [("nn", 1), ("cr", 2)])
def test_tile_invariance(ortho_scene, kernel, factor):
    dsm = _raster(ortho_scene.truth_dsm)
    src = ImageSource.from_file(ortho_scene.views[1])
    p = OrthoSpec(kernel=kernel)
    bounds = (ortho_scene.grid.x0 + 20, ortho_scene.grid.y0 - 100, ortho_scene.grid.x0 + 100, ortho_scene.grid.y0 - 10)
    a = orthorectify(src, dsm, p, factor=factor, chunk=64, bounds=bounds)
    b = orthorectify(src, dsm, p, factor=factor, chunk=512, bounds=bounds)
    assert a.shape == (180 * factor, 160 * factor) and a.data.chunksize == (64, 64)
    va = a.values
    np.testing.assert_array_equal(va, b.values)
    assert np.isnan(va).any() and np.isfinite(va).mean() > 0.8


def _frame_setup(flat=100.0):
    crs, e0, n0 = "EPSG:32631", 640000.0, 4890000.0
    cam = FrameCamera(1000.0, 1000.0, 320.5, 240.5, 480, 640, crs, (e0, n0, flat + 60.0),
                      rotation_nadir(20.0, 1.5, -2.0), k1=-0.05, k2=0.01, p1=2e-4, p2=-1e-4, source="frame")

    def texture(e, n):
        return 1000.0 + 300.0 * np.sin(2 * np.pi * (e - e0) / 1.7) * np.cos(2 * np.pi * (n - n0) / 2.3)

    rows, cols = np.meshgrid(np.arange(480) + 0.5, np.arange(640) + 0.5, indexing="ij")
    e, n = cam.localize_xyz(rows, cols, flat)
    image = texture(e, n).astype(np.float32)
    grid = GroundGrid(crs, e0 - 6.4, n0 + 6.4, 0.2, 64, 64, 32)
    dsm = grid_array(grid, fill=flat).compute()
    return cam, image, grid, dsm, texture


def test_frame_camera_ortho_reproduces_analytic_texture():
    cam, image, grid, dsm, texture = _frame_setup()
    o = orthorectify(ImageSource.from_array(image, cam), dsm, OrthoSpec(kernel="cs"), factor=2, chunk=32)
    X, Y = np.meshgrid(o.x.values, o.y.values)
    err = o.values - texture(X, Y)
    assert np.isfinite(err).all()
    assert np.abs(err).max() < 1.5  # DN of a 300 DN sine sampled at ~0.06 m GSD; measured 0.84


def test_bad_inputs():
    cam, image, grid, dsm, _ = _frame_setup()
    src = ImageSource.from_array(image, cam, name="frame.tif")
    away = ImageSource.from_array(image, cam.replace(position=(cam.position[0] + 1000, cam.position[1], 160.0)),
                                  name="far.tif")
    with pytest.raises(NoOverlapError, match="far.tif: its camera does not see the ground of the DSM"):
        orthorectify(away, dsm)
    with pytest.raises(GridError, match=r"bounds: .* is not covered by the DSM"):
        orthorectify(src, dsm, bounds=(grid.x0 - 50, grid.y0 - 5, grid.x0 + 5, grid.y0))
    with pytest.raises(GridError, match="the ortho is asked in EPSG:32632 but the DSM is in EPSG:32631"):
        orthorectify(src, dsm, crs="EPSG:32632")
    with pytest.raises(GridError, match="no height in the region"):
        orthorectify(src, dsm * np.nan)
    with pytest.raises(InvalidOptionError, match="factor: must be an integer >= 1, got 0"):
        orthorectify(src, dsm, factor=0)
    with pytest.raises(InvalidOptionError, match="factor: must be an integer >= 1, got 1.5"):
        orthorectify(src, dsm, factor=1.5)
    with pytest.raises(InvalidOptionError, match=r"--resolution: 0.3 m does not divide the DSM's 0.5 m cells"):
        resolution_factor(0.5, 0.3)
    assert resolution_factor(0.5, 0.125) == 4


@pytest.mark.parametrize("field, value, message", [
    ("kernel", "lanczos", r"unknown interpolation kernel 'lanczos'; known: \['bl', 'cr', 'cs', 'nn'\]"),
    ("step", 0.0, "greater than 0"),
    ("step", float("nan"), "greater than 0"),
    ("occlusion_tolerance", -0.1, "greater than or equal to 0"),
])
def test_spec_refuses_bad_parameters_at_their_field(field, value, message):
    """What the parameters' checks refuse is a validation error located at the field."""
    with pytest.raises(ValidationError, match=message) as info:
        OrthoSpec(**{field: value})
    assert [e["loc"] for e in info.value.errors()] == [(field,)]


def test_spec_keeps_the_kernel_as_written_and_defaults():
    """The kernel is matched in any case but kept as typed (the fingerprint's
    parameters are the recipe's); the defaults are the documented ones."""
    assert OrthoSpec(kernel="CS").kernel == "CS"
    assert OrthoSpec().model_dump() == {"kernel": "bl", "occlusion": True, "occlusion_tolerance": None, "step": 0.5}


def test_step_is_the_ray_marching_step(ortho_scene):
    """``step`` is the ray-marching step: a coarse one (8 DSM cells) jumps
    over thin occluders, so it hides fewer cells than the default."""
    dsm = _raster(ortho_scene.truth_dsm)
    src = ImageSource.from_file(ortho_scene.views[1])

    def nans(spec):
        return int(np.isnan(orthorectify(src, dsm, spec, chunk=512).values).sum())

    seen_nowhere = nans(OrthoSpec(occlusion=False))  # outside the image only; measured 6510
    # measured 7202 (step 0.5 cells, the default) and 6787 (step 8): 692 and 277 hidden cells
    assert seen_nowhere < nans(OrthoSpec(step=8.0)) < nans(OrthoSpec()) - 300
