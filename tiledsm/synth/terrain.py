"""The synthetic world: relief, buildings, trees and ground albedo.

Everything is a function of absolute local coordinates ``(x, y)`` (metres
east and north of the scene origin), so any window evaluates identically
whatever the tiling:

- relief: a :class:`~tiledsm.synth.noise.SpectralField` with a power-law
  spectrum (fractal terrain), plus a base height (ellipsoidal metres);
- buildings: at most one per cell of a ``building_cell`` lattice, present
  with a probability driven by a smooth "urban density" field; rotated
  rectangles with vertical walls and a flat or gabled roof standing on the
  relief height at their centre;
- trees: at most one per cell of a ``tree_cell`` lattice inside patches of
  a smooth "vegetation" field; dome-topped crowns with steep sides, which
  make rough vegetation-like canopy;
- albedo: ground texture with a natural ``1/f`` amplitude spectrum
  (:mod:`tiledsm.synth.texture`), per-building roof albedo and darker trees;
- optionally one tall tower (:mod:`tiledsm.synth.tower`).

Surface classes in the label map: 0 ground, 1 building, 2 tree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

from tiledsm.synth.noise import SpectralField, cell_uniforms, power_law_field
from tiledsm.synth.texture import TextureParams, ground_albedo, make_texture_field
from tiledsm.synth.tower import Tower, apply_tower

__all__ = ["TerrainParams", "World", "make_world"]


@dataclass(frozen=True)
class TerrainParams:
    """Parameters of the synthetic ground (lengths in metres).

    Attributes
    ----------
    base_height : float
        Mean surface height, metres above the WGS84 ellipsoid.
    relief_rms : float
        Standard deviation of the fractal relief over its largest wavelength.
    relief_beta : float
        Spectral exponent of the relief's 2-D power spectrum.
    relief_wavelengths : (float, float)
        Shortest and longest relief wavelengths.
    building_cell : float
        Lattice step of the building placement (one building at most per cell).
    building_density : float
        Largest probability that a cell holds a building (in dense areas).
    building_size : (float, float)
        Range of building footprint sides.
    building_height : (float, float)
        Range of wall heights.
    gable_fraction : float
        Fraction of buildings with a gabled roof (others are flat).
    tree_cell : float
        Lattice step of the tree placement.
    tree_density : float
        Probability that a cell inside a vegetation patch holds a tree.
    tree_radius, tree_height : (float, float)
        Ranges of crown radius and tree height.
    vegetation_cover : float
        Approximate fraction of the ground inside vegetation patches.
    """

    base_height: float = 350.0
    relief_rms: float = 30.0
    relief_beta: float = 3.4
    relief_wavelengths: tuple[float, float] = (4.0, 6000.0)
    building_cell: float = 36.0
    building_density: float = 0.9
    building_size: tuple[float, float] = (8.0, 23.0)
    building_height: tuple[float, float] = (4.0, 24.0)
    gable_fraction: float = 0.5
    tree_cell: float = 5.0
    tree_density: float = 0.6
    tree_radius: tuple[float, float] = (1.5, 3.5)
    tree_height: tuple[float, float] = (4.0, 14.0)
    vegetation_cover: float = 0.3

    @property
    def object_height_max(self) -> float:
        """Largest height an object (building with ridge, tree) adds, metres."""
        ridge = 0.5 * self.building_size[1] * math.tan(math.radians(40.0))
        return max(self.building_height[1] + ridge, self.tree_height[1]) + 1.0


@dataclass(frozen=True, eq=False)
class World:
    """A deterministic synthetic world (see module docstring).

    Build it with :func:`make_world`. Coordinates are local metres relative
    to the scene origin; heights are metres above the WGS84 ellipsoid. An
    optional :class:`~tiledsm.synth.tower.Tower` (``tower``, added with
    ``dataclasses.replace(world, tower=place_tower(...))``) is drawn over
    the relief, buildings and trees.
    """

    seed: int
    terrain: TerrainParams
    texture: TextureParams
    relief: SpectralField
    urban: SpectralField
    vegetation: SpectralField
    albedo_field: SpectralField
    veg_threshold: float = field(default=0.0)
    #: optional tall tower (:mod:`tiledsm.synth.tower`), drawn over everything else
    tower: Tower | None = field(default=None)

    # ----------------------------------------------------------- bounds
    def height_bounds(self, xmin: float, xmax: float, ymin: float, ymax: float) -> tuple[float, float]:
        """Guaranteed bounds of the surface height over a rectangle.

        The relief is sampled on a coarse grid and widened by the largest
        change possible between samples
        (:meth:`SpectralField.variation_bound`); objects add at most
        :attr:`TerrainParams.object_height_max`.
        """
        step = 8.0
        xs = np.arange(xmin, xmax + step, step)
        ys = np.arange(ymin, ymax + step, step)
        r = self.relief.grid(xs, ys, dtype=np.float64) + self.terrain.base_height
        slack = self.relief.variation_bound(step / math.sqrt(2.0)) + 0.01
        lo, hi = float(r.min() - slack), float(r.max() + slack + self.terrain.object_height_max)
        if self.tower is not None and self.tower.intersects(xmin, xmax, ymin, ymax):
            hi = max(hi, self.tower.roof_height + 0.01)
        return lo, hi

    # ----------------------------------------------------------- evaluate
    def evaluate(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Surface height, albedo and class on a separable grid.

        Parameters
        ----------
        x, y : numpy.ndarray
            1-D local coordinates, metres (east, north); the result's
            element ``[i, j]`` is at ``(x[j], y[i])``.

        Returns
        -------
        height : numpy.ndarray
            float32, metres above the WGS84 ellipsoid.
        albedo : numpy.ndarray
            float32, in [0, 1].
        label : numpy.ndarray
            uint8: 0 ground, 1 building, 2 tree.
        """
        x = np.asarray(x, np.float64)
        y = np.asarray(y, np.float64)
        tp = self.terrain
        height = self.relief.grid(x, y) + np.float32(tp.base_height)
        tex = self.albedo_field.grid(x, y)
        albedo = ground_albedo(tex, self.texture)
        label = np.zeros(height.shape, np.uint8)
        bcell, bi0, bj0, bpar = self._buildings(x, y)
        tcell, ti0, tj0, tpar = self._trees(x, y)
        tower = self.tower
        bare = height.copy() if tower is not None and tower.params.clearance_m > 0 else None
        _place_objects(x, y, height, albedo, label, tex, bcell, bi0, bj0, bpar, tcell, ti0, tj0, tpar)
        if tower is not None:
            apply_tower(tower, x, y, height, albedo, label, tex, bare, self.texture)
        return height, albedo, label

    def _lattice(self, x, y, cell, pad):
        i0 = int(math.floor(y.min() / cell)) - pad
        i1 = int(math.floor(y.max() / cell)) + pad
        j0 = int(math.floor(x.min() / cell)) - pad
        j1 = int(math.floor(x.max() / cell)) + pad
        I, J = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
        return i0, j0, I, J

    def _buildings(self, x, y):
        tp = self.terrain
        cell = tp.building_cell
        i0, j0, I, J = self._lattice(x, y, cell, 0)
        u = cell_uniforms(self.seed, 1, I, J, 10)
        cx0 = (J + 0.5) * cell
        cy0 = (I + 0.5) * cell
        density = tp.building_density * np.clip(self.urban.points(cx0, cy0) + 0.5, 0.0, 1.0)
        lo, hi = tp.building_size
        length = lo + (hi - lo) * u[..., 1]
        width = lo + (length - lo) * u[..., 2]
        half_l, half_w = 0.5 * length, 0.5 * width
        radius = np.hypot(half_l, half_w)
        slack = np.maximum(0.5 * cell - radius - 1.0, 0.0)
        cx = cx0 + (2 * u[..., 3] - 1) * slack
        cy = cy0 + (2 * u[..., 4] - 1) * slack
        angle = np.pi * u[..., 5]
        walls = tp.building_height[0] + (tp.building_height[1] - tp.building_height[0]) * u[..., 6]
        base = self.relief.points(cx, cy) + tp.base_height
        gabled = u[..., 7] < tp.gable_fraction
        pitch = np.radians(20.0 + 20.0 * u[..., 8])
        ridge = np.where(gabled, half_w * np.tan(pitch), 0.0)
        roof_albedo = 0.2 + 0.55 * u[..., 9]
        exists = (u[..., 0] < density) & (radius + 1.0 < 0.5 * cell)
        par = np.stack(
            [exists.astype(float), cx, cy, np.cos(angle), np.sin(angle), half_l, half_w,
             base + walls, ridge, roof_albedo],
            axis=-1,
        )
        return cell, i0, j0, np.ascontiguousarray(par)

    def _trees(self, x, y):
        tp = self.terrain
        cell = tp.tree_cell
        i0, j0, I, J = self._lattice(x, y, cell, 1)
        u = cell_uniforms(self.seed, 2, I, J, 6)
        cx = (J + 0.5 + 0.6 * (u[..., 1] - 0.5)) * cell
        cy = (I + 0.5 + 0.6 * (u[..., 2] - 0.5)) * cell
        patch = self.vegetation.points(cx, cy) > self.veg_threshold
        exists = patch & (u[..., 0] < tp.tree_density)
        radius = tp.tree_radius[0] + (tp.tree_radius[1] - tp.tree_radius[0]) * u[..., 3]
        h = tp.tree_height[0] + (tp.tree_height[1] - tp.tree_height[0]) * u[..., 4]
        albedo = 0.08 + 0.1 * u[..., 5]
        par = np.stack([exists.astype(float), cx, cy, radius, h, albedo], axis=-1)
        return cell, i0, j0, np.ascontiguousarray(par)


@numba.njit(nogil=True, cache=True)
def _place_objects(x, y, height, albedo, label, tex, bcell, bi0, bj0, bpar, tcell, ti0, tj0, tpar):
    ny, nx = height.shape
    nbi, nbj = bpar.shape[0], bpar.shape[1]
    nti, ntj = tpar.shape[0], tpar.shape[1]
    for i in range(ny):
        yy = y[i]
        for j in range(nx):
            xx = x[j]
            ground = height[i, j]
            t = tex[i, j]
            # trees: the highest crown among the 3 x 3 neighbouring cells
            ci = int(math.floor(yy / tcell)) - ti0
            cj = int(math.floor(xx / tcell)) - tj0
            best = ground
            best_a = -1.0
            for di in range(-1, 2):
                ii = ci + di
                if ii < 0 or ii >= nti:
                    continue
                for dj in range(-1, 2):
                    jj = cj + dj
                    if jj < 0 or jj >= ntj or tpar[ii, jj, 0] == 0.0:
                        continue
                    dx = xx - tpar[ii, jj, 1]
                    dy = yy - tpar[ii, jj, 2]
                    r = tpar[ii, jj, 3]
                    d2 = (dx * dx + dy * dy) / (r * r)
                    if d2 < 1.0:
                        z = ground + tpar[ii, jj, 4] * (0.6 + 0.4 * math.sqrt(1.0 - d2))
                        if z > best:
                            best = z
                            best_a = tpar[ii, jj, 5] * (1.0 + 0.5 * t)
            if best_a >= 0.0:
                height[i, j] = best
                albedo[i, j] = min(max(best_a, 0.02), 1.0)
                label[i, j] = 2
            # buildings: the one of this lattice cell, if any (it wins over trees)
            bi = int(math.floor(yy / bcell)) - bi0
            bj = int(math.floor(xx / bcell)) - bj0
            if bi < 0 or bi >= nbi or bj < 0 or bj >= nbj or bpar[bi, bj, 0] == 0.0:
                continue
            dx = xx - bpar[bi, bj, 1]
            dy = yy - bpar[bi, bj, 2]
            c = bpar[bi, bj, 3]
            s = bpar[bi, bj, 4]
            u = c * dx + s * dy
            v = -s * dx + c * dy
            hl = bpar[bi, bj, 5]
            hw = bpar[bi, bj, 6]
            if abs(u) <= hl and abs(v) <= hw:
                z = bpar[bi, bj, 7] + bpar[bi, bj, 8] * (1.0 - abs(v) / hw)
                height[i, j] = max(z, ground)
                albedo[i, j] = min(max(bpar[bi, bj, 9] * (1.0 + 0.3 * t), 0.02), 1.0)
                label[i, j] = 1


def make_world(
    seed: int = 0,
    gsd: float = 0.5,
    terrain: TerrainParams | None = None,
    texture: TextureParams | None = None,
) -> World:
    """Draw a world from a seed.

    Parameters
    ----------
    seed : int
        Fixes every random choice (fields and per-cell objects).
    gsd : float
        Image ground sample distance, metres; the texture is band-limited
        just below the Nyquist frequency of images at that GSD.
    terrain, texture : optional
        Parameters; defaults when omitted.
    """
    terrain = terrain or TerrainParams()
    texture = texture or TextureParams()
    rng = np.random.default_rng([int(seed), 20240611])
    relief = power_law_field(rng, terrain.relief_wavelengths, terrain.relief_beta, terrain.relief_rms, 16)
    urban = power_law_field(rng, (150.0, 2000.0), 3.0, 0.5, 4)
    vegetation = power_law_field(rng, (40.0, 1500.0), 3.0, 1.0, 6)
    albedo_field = make_texture_field(rng, gsd, texture)
    # threshold so that roughly `vegetation_cover` of the ground is in patches
    # (the field is close to Gaussian with unit standard deviation)
    from scipy.stats import norm

    thr = float(norm.ppf(1.0 - terrain.vegetation_cover) * vegetation.rms)
    return World(int(seed), terrain, texture, relief, urban, vegetation, albedo_field, thr)
