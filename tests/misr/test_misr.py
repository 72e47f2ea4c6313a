"""Multi-image SR: IBP tile invariance and convergence, registration,
resolving power, errors, and SR-O vs SR-R vs SR-S on a synthetic UAV block."""

import numpy as np
import pytest
from scipy import ndimage

from tiledsm.misr.ibp import PSF, Observations, ibp
from tiledsm.misr.methods import MISRError, SRInputs, radial_select, sr_o, sr_r, sr_s
from tiledsm.misr.metrics import resolved_px, stripe_contrast
from tiledsm.misr.register import register
from tiledsm.sr.metrics import psnr
from tiledsm.synth.uav import UAVParams, chart_layout, make_uav_scene


def _box_observations(hr, scale, n_images, rng):
    """LR pixels = exact box means of ``scale x scale`` HR cells at random sub-pixel offsets."""
    us, vs, cs, ims = [], [], [], []
    n = hr.shape[0]
    for k in range(n_images):
        oy, ox = rng.integers(0, scale, 2)
        lr_v = np.arange(oy + scale / 2, n - scale / 2, scale)
        lr_u = np.arange(ox + scale / 2, n - scale / 2, scale)
        V, U = np.meshgrid(lr_v, lr_u, indexing="ij")
        # box mean of cells [v - s/2, v + s/2) (integer-aligned: even scale)
        c = np.array([[hr[int(v - scale / 2):int(v + scale / 2), int(u - scale / 2):int(u + scale / 2)].mean()
                       for u in lr_u] for v in lr_v])
        us.append(U.ravel()); vs.append(V.ravel()); cs.append(c.ravel()); ims.append(np.full(c.size, k))
    return Observations(np.concatenate(us), np.concatenate(vs), np.concatenate(cs), np.concatenate(ims))


def test_ibp_converges_and_is_tile_invariant():
    rng = np.random.default_rng(0)
    hr = ndimage.gaussian_filter(rng.uniform(0, 255, (96, 96)), 1.0)
    obs = _box_observations(hr, 2, 4, rng)
    init = ndimage.uniform_filter(hr, 4)
    a, ra = ibp(init, obs, PSF("square"), 2, chunk=32, max_iter=8)
    b, rb = ibp(init, obs, PSF("square"), 2, chunk=512, max_iter=8)
    np.testing.assert_array_equal(a, b)
    assert ra["iterations"] == rb["iterations"] == 8
    np.testing.assert_allclose(ra["errors"], rb["errors"], rtol=1e-12)  # sums in another order
    e = np.array(ra["errors"])
    assert np.all(np.diff(e) < 0) and e[-1] < 0.1 * e[0]  # E(t) falls every iteration
    assert psnr(hr, a, data_range=255, border=4) > psnr(hr, init, data_range=255, border=4) + 6
    # stopping rule: E(t) <= Te
    _, rg = ibp(init, obs, PSF("gaussian", 1.0), 2, chunk=48, max_iter=5)
    _, rc = ibp(init, obs, PSF("gaussian", 1.0), 2, chunk=48, max_iter=50, te=rg["errors"][3])
    assert rc["iterations"] == 3 and rc["errors"] == rg["errors"][:4]


def test_register_recovers_translation_and_grey_levels():
    rng = np.random.default_rng(1)
    ref = ndimage.gaussian_filter(rng.uniform(0, 255, (120, 120)), 2.0)
    moving = 1.2 * ndimage.shift(ref, (0.3, -0.45), order=3, mode="nearest") + 7.0  # content of ref[q] at q + t
    moving[:5] = np.nan
    reg = register(moving, ref)
    assert reg.ty == pytest.approx(0.3, abs=0.02) and reg.tx == pytest.approx(-0.45, abs=0.02)
    # least squares on the (bilinearly) warped ortho: slightly steeper than 1/1.2 (measured 0.856)
    assert reg.gain == pytest.approx(1 / 1.2, abs=0.03) and reg.offset == pytest.approx(-7 / 1.2, abs=4.0)  # measured -9.4


def test_resolving_power_on_chart():
    chart = chart_layout(192)
    img = np.full((192, 192), 128.0)
    for k, r0, r1, c0, c1 in chart:
        cols = np.arange(c1 - c0)
        img[r0:r1, c0:c1] = np.where((cols // k) % 2 == 1, 230.0, 30.0)
    assert resolved_px(img, chart) == 1
    assert stripe_contrast(img, chart[3]) == pytest.approx(0.78 * 4 / np.pi, rel=0.05)  # square wave fundamental
    # a Gaussian of sigma 2 cells keeps exp(-2 pi^2 s^2 / (2k)^2) of the stripes' fundamental on an
    # endless grating (k = 2: 0.007, k = 3: 0.11); the 2-period groups leak a little more (0.08, 0.21)
    blurred = ndimage.gaussian_filter1d(img, 2.0, axis=1)
    assert stripe_contrast(blurred, chart[1]) < 0.1 <= stripe_contrast(blurred, chart[2])
    assert resolved_px(blurred, chart) == 3


@pytest.fixture(scope="module")
def uav():
    p = UAVParams(scale=2, frames=16, rows=120, cols=160, roi=160, supersample=2, seed=2)
    sc = make_uav_scene(p)
    return sc, SRInputs(sc.frames, sc.cameras, sc.grid, sc.dsm, 2)


def test_uav_scene_truth(uav):
    sc, _ = uav
    assert len(sc.frames) == 16 and sc.truth.shape == (160, 160)
    assert resolved_px(sc.truth, sc.chart) == 1
    r, c, rad = sc.pole
    assert sc.dsm[int(r), int(c)] == pytest.approx(np.median(sc.dsm) + 1.0, abs=0.1)  # the pole's top
    assert sc.truth[int(r), int(c)] == pytest.approx(235.0)


@pytest.mark.slow
def test_sr_o_beats_sr_r_beats_nothing(uav):
    sc, inp = uav
    s, _ = sr_s(inp, "cr")
    r, rr = sr_r(inp, "cr")
    o, ro = sr_o(inp, PSF("square"), "cr", max_iter=8)
    q = {k: psnr(sc.truth, v, data_range=255, border=2) for k, v in (("s", s), ("r", r), ("o", o))}
    assert rr["images"] == 16 and ro["iterations"] == 8
    assert q["o"] > q["r"] + 0.8 and q["r"] > q["s"]
    assert resolved_px(o, sc.chart) <= resolved_px(s, sc.chart)
    with pytest.raises(MISRError, match="SR-O: needs at least 2 images, got 1"):
        sr_o(inp, indices=radial_select(inp, 0.0) or [0])
    with pytest.raises(MISRError, match="SR-R: needs at least 2 images"):
        sr_r(inp, indices=[3])


def test_sr_refuses_when_registration_leaves_one_image(uav, monkeypatch):
    """When ECC registers no image but the reference, SR-R and SR-O stop
    with :class:`RegistrationError` (a one-image "multi-image SR" would be
    scored as if it were one)."""
    import tiledsm.misr.methods as methods
    from tiledsm.misr.methods import RegistrationError

    sc, _ = uav
    fresh = SRInputs(sc.frames, sc.cameras, sc.grid, sc.dsm, 2)  # its own cache of registrations
    monkeypatch.setattr(methods, "register", lambda moving, reference, *a, **k: methods.Registration(ecc=float("nan")))
    with pytest.raises(RegistrationError, match="only 1 of 16 images registered"):
        sr_r(fresh, "cr")
    with pytest.raises(RegistrationError, match="only 1 of"):
        sr_o(fresh, PSF("square"), "cr", max_iter=2)
