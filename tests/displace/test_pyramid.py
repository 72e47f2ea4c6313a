"""Coarse to fine (tiledsm.displace.pyramid): a 24 px strike-slip step,
measured at the fine level's precision on both sides, not smeared, and
independent of the chunking."""

import numpy as np
import pytest
from scipy import ndimage
from shift_cases import ortho, texture

from tiledsm.displace import CorrelationParams, correlate_orthos

N = 384
DY, DX = -14.3, 19.6  # 24.3 px along the trace


@pytest.fixture(scope="module")
def step_pair():
    base = texture(n=N, seed=2)
    yy, xx = np.mgrid[0:N, 0:N].astype(float)
    # the trace runs along the motion through the centre (pixel-index coordinates); its right side moved
    right = (xx - N / 2) * (-DY) + (yy - N / 2) * DX >= 0
    moved = ndimage.map_coordinates(base, [yy - DY, xx - DX], order=5, mode="reflect")
    return ortho(base), ortho(np.where(right, moved, base))


def _distance_px(p: CorrelationParams):
    c = (np.arange(N // p.step) + 0.5) * p.step - 0.5  # cell centres in pixel-index coordinates
    cy, cx = np.meshgrid(c, c, indexing="ij")
    return ((cx - N / 2) * (-DY) + (cy - N / 2) * DX) / np.hypot(DY, DX)


def test_a_step_beyond_the_search_is_measured_without_smearing(step_pair):
    p = CorrelationParams(levels=2)
    assert p.reach == 32
    f = correlate_orthos(*step_pair, p, chunk=1024).compute()
    dy, dx = -f.dN.values / 0.5, f.dE.values / 0.5
    d = _distance_px(p)
    ty, tx = np.where(d >= 0, DY, 0.0), np.where(d >= 0, DX, 0.0)
    inner = np.zeros(d.shape, bool)
    inner[6:-6, 6:-6] = True  # the moved content comes from 24 px away: off the texture near its edges
    far = inner & (np.abs(d) > 2 * p.window)
    err = np.hypot(dy - ty, dx - tx)
    assert np.isfinite(err[far]).all()
    assert np.sqrt(np.mean(err[far] ** 2)) < 0.01  # measured 0.0023 px
    # a window straddling the trace takes its dominant side: wrong-side cells only within half a window of it
    wrong = inner & np.isfinite(err) & (err > 0.5)
    assert np.abs(d[wrong]).max(initial=0) <= p.window / 2  # measured 3.0 px
    assert np.isfinite(err[inner & (np.abs(d) > p.window / 2)]).mean() > 0.97  # measured 1.0
    # one level: the moved side is beyond the 8 px search, NaN
    one = correlate_orthos(*step_pair, CorrelationParams(), chunk=1024).compute()
    assert np.isfinite(one.dE.values[far & (d > 0)]).mean() < 0.02


@pytest.mark.slow
def test_the_pyramid_does_not_depend_on_the_chunking(step_pair):
    p = CorrelationParams(levels=2)
    a = correlate_orthos(*step_pair, p, chunk=200).compute()
    b = correlate_orthos(*step_pair, p, chunk=1024).compute()
    for v in ("dE", "dN", "quality"):
        # identical but for the last bits of FFTs batched differently (1e-13 m)
        np.testing.assert_allclose(a[v].values, b[v].values, rtol=0, atol=1e-9)
