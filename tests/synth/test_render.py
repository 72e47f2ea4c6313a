"""Rendering: analytic flat ground, occlusion, tiling."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from tiledsm.geometry.pushbroom import PushbroomCamera
from tiledsm.synth import RadiometryParams, make_world, render_window

E0, N0 = 650000.0, 4896000.0


@dataclass(frozen=True)
class FlatGround:
    """Level ground at ``h`` with albedo ``0.4 + 0.2 cos(k.x)`` and an
    optional box building (centre, half side, top height)."""

    h: float = 100.0
    box: tuple | None = None

    @staticmethod
    def albedo(x, y):
        return 0.4 + 0.2 * np.cos(2 * np.pi * (x / 5.0 + y / 7.0) + 0.3)

    def evaluate(self, x, y):
        X, Y = np.meshgrid(np.asarray(x, float), np.asarray(y, float))
        h = np.full(X.shape, self.h, np.float32)
        lab = np.zeros(X.shape, np.uint8)
        if self.box is not None:
            (cx, cy), half, top = self.box
            inside = (np.abs(X - cx) <= half) & (np.abs(Y - cy) <= half)
            h[inside] = top
            lab[inside] = 1
        return h, self.albedo(X, Y).astype(np.float32), lab

    def height_bounds(self, *box):
        return self.h - 1.0, (self.box[2] if self.box else self.h) + 1.0


def _cam(pitch=0.0, roll=0.0, n=64, h0=100.0):
    return PushbroomCamera("EPSG:32631", E0, N0, h0, n, n, 0.5, pitch_deg=pitch, roll_deg=roll)


def test_flat_ground_pixel_equals_texture_at_localized_point():
    ground = FlatGround()
    rad = RadiometryParams(psf_sigma=0.0, noise=0.0, oversample=4)
    cam = _cam(pitch=12.0, roll=3.0)
    dn, radiance, xyz = render_window(ground, cam, (E0, N0), ground.height_bounds(), (0, 64), (0, 64), rad,
                                      truth=True)
    rows, cols = np.meshgrid(np.arange(64) + 0.5, np.arange(64) + 0.5, indexing="ij")
    x, y = cam.localize_xy(rows, cols, ground.h)
    np.testing.assert_allclose(xyz[..., 0], x - E0, atol=1e-3)
    np.testing.assert_allclose(xyz[..., 1], y - N0, atol=1e-3)
    np.testing.assert_allclose(xyz[..., 2], ground.h, atol=1e-3)
    shade = rad.ambient + (1 - rad.ambient) * rad.sun[2]
    expected = ground.albedo(x - E0, y - N0) * shade
    # bilinear interpolation of a 5 m-wavelength texture sampled every 0.125 m
    assert np.abs(radiance - expected).max() < 0.01 * 0.2
    np.testing.assert_array_equal(dn, np.floor(rad.offset + rad.gain * radiance.astype(float) + 0.5).astype(np.uint16))


def test_tall_building_hides_the_ground_behind_it():
    top = 130.0
    ground = FlatGround(box=((0.0, 0.0), 6.0, top))
    rad = RadiometryParams(psf_sigma=0.0, noise=0.0)
    cam = _cam(pitch=20.0, n=96)
    # the satellite is on the side of -parallax... parallax points towards it
    towards = cam.parallax() / np.linalg.norm(cam.parallax())
    behind = -towards * 9.0  # ground 3 m behind the far wall, inside the 30 m * tan(20) shadow
    front = towards * 9.0
    for point, hidden in ((behind, True), (front, False)):
        r, c = cam.project_xy(E0 + point[0], N0 + point[1], ground.h)
        i, j = int(r), int(c)
        _, _, xyz = render_window(ground, cam, (E0, N0), ground.height_bounds(), (i, i + 1), (j, j + 1), rad,
                                  truth=True)
        z = xyz[0, 0, 2]
        if hidden:
            assert z > ground.h + 5.0, z  # sees the roof or the wall
            assert np.hypot(*(xyz[0, 0, :2] - point)) > 2.0
        else:
            assert abs(z - ground.h) < 1e-3
    # from nadir the same ground point is visible
    nadir = _cam(pitch=0.0, n=96)
    r, c = nadir.project_xy(E0 + behind[0], N0 + behind[1], ground.h)
    _, _, xyz = render_window(ground, nadir, (E0, N0), ground.height_bounds(), (int(r), int(r) + 1),
                              (int(c), int(c) + 1), rad, truth=True)
    assert abs(xyz[0, 0, 2] - ground.h) < 1e-3


def test_wall_hit_lies_on_the_wall():
    top = 130.0
    ground = FlatGround(box=((0.0, 0.0), 6.0, top))
    cam = _cam(pitch=20.0, n=96)
    rad = RadiometryParams(psf_sigma=0.0, noise=0.0, oversample=4)
    _, _, xyz = render_window(ground, cam, (E0, N0), ground.height_bounds(), (0, 96), (0, 96), rad, truth=True)
    z = xyz[..., 2]
    wall = (z > ground.h + 1) & (z < top - 1)
    assert wall.sum() > 50  # the oblique view sees a wall
    x, y = xyz[..., 0][wall], xyz[..., 1][wall]
    # wall points lie on the box outline, within one lattice step (0.125 m)
    d = np.maximum(np.abs(x), np.abs(y))
    assert np.all(np.abs(d - 6.0) < 0.13)


@pytest.mark.parametrize("tile", [32, 47])
def test_tiled_rendering_equals_untiled(tile):
    world = make_world(0, 0.5)
    cam = _cam(pitch=-11.0, roll=1.0, n=96, h0=350.0)
    hr = world.height_bounds(-150, 150, -150, 150)
    rad = RadiometryParams()
    full = render_window(world, cam, (E0, N0), hr, (0, 96), (0, 96), rad, seed=1, view=0)
    tiled = np.zeros_like(full)
    for r0 in range(0, 96, tile):
        for c0 in range(0, 96, tile):
            r1, c1 = min(r0 + tile, 96), min(c0 + tile, 96)
            tiled[r0:r1, c0:c1] = render_window(world, cam, (E0, N0), hr, (r0, r1), (c0, c1), rad, seed=1, view=0)
    diff = np.abs(full.astype(int) - tiled.astype(int))
    # float32 sums differ in their last bits between window sizes: rare 1-DN rounding flips
    assert diff.max() <= 1 and (diff > 0).mean() < 5e-3
    assert full.std() > 100  # textured


def test_noise_is_deterministic_and_has_the_asked_deviation():
    world = make_world(0, 0.5)
    cam = _cam(n=64, h0=350.0)
    hr = world.height_bounds(-100, 100, -100, 100)
    clean = render_window(world, cam, (E0, N0), hr, (0, 64), (0, 64), RadiometryParams(noise=0.0), seed=1)
    noisy = render_window(world, cam, (E0, N0), hr, (0, 64), (0, 64), RadiometryParams(noise=5.0), seed=1)
    again = render_window(world, cam, (E0, N0), hr, (0, 64), (0, 64), RadiometryParams(noise=5.0), seed=1)
    other = render_window(world, cam, (E0, N0), hr, (0, 64), (0, 64), RadiometryParams(noise=5.0), seed=2)
    assert np.array_equal(noisy, again) and not np.array_equal(noisy, other)
    assert 4.5 < (noisy.astype(float) - clean).std() < 5.5
