"""Synthetic UAV block with truth, for multi-image super-resolution.

A small ground scene seen by many overlapping nadir frames
(:class:`~tiledsm.geometry.frame.FrameCamera`):

- **ground**: a random texture (power-law field, natural-image spectrum)
  on a smooth relief of a few centimetres, a **resolution chart** of stripe
  groups ``k = 1..8`` whose bars are ``k`` HR pixels wide (two periods,
  bars varying along x), and a **thin vertical pole** (white top);
- **frames**: ``rows x cols`` images from a serpentine flight pattern over
  the region of interest (ROI) with sub-pixel jitter, rendered with the
  true poses; the cameras handed out (``nominal``) carry small pose errors
  (position and attitude), as a UAV's GNSS/IMU would;
- **sensor**: each pixel integrates its footprint (``supersample`` ^2 rays),
  a lens blur that grows with the radial distance from the principal
  point (Gaussian, ``sigma(r) = blur_centre + (blur_edge - blur_centre)
  (r / r_max)^2`` LR pixels), Gaussian noise;
- **truth** on the HR grid over the ROI (``lr_gsd / scale`` cells): the
  ortho seen from straight above (box average of ``truth_supersample`` ^2
  samples per cell, no blur, no noise) and the DSM (relief, the pole's top
  on the pole's cells).

Conventions: world frame = ``crs`` easting/northing and ellipsoidal heights
(metres); digital numbers ``DN = dn_offset + dn_gain * albedo`` in 0..255;
pixel coordinates GDAL's. Everything is computed in memory (a few hundred
thousand pixels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from tiledsm.geometry.frame import FrameCamera, rotation_nadir
from tiledsm.geometry.grid import GroundGrid
from tiledsm.synth.noise import power_law_field

__all__ = ["UAVParams", "UAVScene", "make_uav_scene", "chart_layout"]

#: bar widths of the chart's stripe groups, HR pixels
GROUPS = tuple(range(1, 9))


@dataclass(frozen=True)
class UAVParams:
    """Parameters of the synthetic UAV block (lengths in metres unless said).

    Attributes
    ----------
    scale : int
        HR grid = LR GSD / scale; the chart's bars are multiples of the HR cell.
    lr_gsd : float
        Frame ground sample distance at nadir.
    roi : int
        ROI side, HR cells.
    frames : int
        Number of frames (16..40), on a serpentine lattice of flight lines.
    rows, cols : int
        Frame size, pixels.
    altitude : float
        Flying height above the ground.
    pixel_size_mm : float
        Detector pitch (focal-plane radii for radial selection).
    position_error, attitude_error_deg : float
        Standard deviations of the nominal poses' errors.
    blur_centre, blur_edge : float
        Lens blur sigma at the principal point and at the frame corner, LR px.
    noise : float
        Noise standard deviation, DN.
    relief : float
        Amplitude of the smooth relief.
    pole_radius, pole_height : float
        The pole.
    supersample, truth_supersample : int
        Rays per pixel side (frames) and samples per HR cell side (truth).
    seed : int
    """

    scale: int = 2
    lr_gsd: float = 0.02
    roi: int = 192
    frames: int = 30
    rows: int = 150
    cols: int = 200
    altitude: float = 30.0
    pixel_size_mm: float = 0.18
    position_error: float = 0.004
    attitude_error_deg: float = 0.005
    blur_centre: float = 0.35
    blur_edge: float = 1.1
    noise: float = 1.0
    relief: float = 0.05
    pole_radius: float = 0.012
    pole_height: float = 1.0
    supersample: int = 3
    truth_supersample: int = 4
    dn_offset: float = 20.0
    dn_gain: float = 215.0
    seed: int = 0
    crs: str = "EPSG:32631"
    origin: tuple[float, float, float] = (500000.0, 4900000.0, 100.0)

    def __post_init__(self) -> None:
        if not 16 <= self.frames <= 40:
            raise ValueError(f"UAVParams.frames must be in 16..40, got {self.frames}")
        if self.scale not in (2, 3, 4):
            raise ValueError(f"UAVParams.scale must be 2, 3 or 4, got {self.scale}")

    @property
    def hr_gsd(self) -> float:
        return self.lr_gsd / self.scale

    @property
    def focal_px(self) -> float:
        return self.altitude / self.lr_gsd


@dataclass(frozen=True, eq=False)
class UAVScene:
    """A synthetic UAV block (:func:`make_uav_scene`).

    Attributes
    ----------
    frames : list of numpy.ndarray
        float32 DN images ``(rows, cols)``.
    cameras : list of FrameCamera
        Nominal cameras (with pose errors): what a user would have.
    true_cameras : list of FrameCamera
        The poses the frames were rendered with.
    grid : GroundGrid
        HR grid over the ROI.
    truth : numpy.ndarray
        True HR ortho, DN.
    dsm : numpy.ndarray
        True DSM on ``grid``, metres.
    chart : list of (k, row0, row1, col0, col1)
        Stripe group ``k`` (bars ``k`` HR px wide) occupies these HR cells.
    pole : (row, col, radius)
        Pole centre and radius, HR cells.
    params : UAVParams
    """

    frames: list
    cameras: list
    true_cameras: list
    grid: GroundGrid
    truth: np.ndarray
    dsm: np.ndarray
    chart: list
    pole: tuple
    params: UAVParams
    paths: dict = field(default_factory=dict)


def chart_layout(roi: int) -> list[tuple[int, int, int, int, int]]:
    """Stripe groups on the HR grid: two rows (groups 1-6 and 7-8), each
    group two bar periods wide (``4 k`` cells) and ``24`` cells tall,
    ``6``-cell gaps, starting 8 cells from the ROI's top-left corner."""
    out, r0, c = [], 8, 8
    for k in GROUPS:
        if k == 7:
            r0, c = r0 + 24 + 10, 8
        w = 4 * k
        if c + w > roi - 4 or r0 + 24 > roi - 4:
            raise ValueError(f"chart_layout: the chart does not fit in a {roi}-cell ROI (need >= 160)")
        out.append((k, r0, r0 + 24, c, c + w))
        c += w + 6
    return out


class _Ground:
    """Albedo, relief and pole of the scene (local metres from the origin)."""

    def __init__(self, p: UAVParams):
        rng = np.random.default_rng(p.seed)
        self.p = p
        self.tex = power_law_field(rng, (2 * p.hr_gsd, 0.6), beta=2.0, rms=0.12, per_octave=6)
        self.rel = power_law_field(rng, (0.8, 4.0), beta=3.0, rms=p.relief / 2, per_octave=4)
        side = p.roi * p.hr_gsd
        self.x0, self.y0 = -side / 2, side / 2  # ROI top-left corner (local)
        self.chart = chart_layout(p.roi)
        # the pole: lower right quarter of the ROI, on a cell centre
        pr, pc = int(p.roi * 0.75), int(p.roi * 0.7)
        self.pole_rc = (pr + 0.5, pc + 0.5)
        self.pole_xy = (self.x0 + (pc + 0.5) * p.hr_gsd, self.y0 - (pr + 0.5) * p.hr_gsd)

    def relief(self, x, y):
        return self.p.origin[2] + self.rel.points(x, y)

    def albedo(self, x, y):
        p = self.p
        a = np.clip(0.5 + self.tex.points(x, y), 0.05, 0.95)
        col = (x - self.x0) / p.hr_gsd
        row = (self.y0 - y) / p.hr_gsd
        for k, r0, r1, c0, c1 in self.chart:
            inside = (row >= r0 - 3) & (row < r1 + 3) & (col >= c0 - 3) & (col < c1 + 3)
            a = np.where(inside, 0.5, a)  # grey surround
            bars = (row >= r0) & (row < r1) & (col >= c0) & (col < c1)
            white = (np.floor((col - c0) / k).astype(np.int64) % 2) == 1
            a = np.where(bars, np.where(white, 0.95, 0.05), a)
        return a

    def pole_top(self):
        return self.relief(np.array(self.pole_xy[0]), np.array(self.pole_xy[1])) + self.p.pole_height


def _render_rays(g: _Ground, cam: FrameCamera, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Albedo seen along the rays of image points (GDAL coordinates):
    the pole (top disk or side) when hit first, else the relief (ray-surface
    intersection by fixed-point iterations)."""
    p = g.p
    E0, N0, _ = p.origin
    x, y = cam.undistort((cols - cam.cx) / cam.fx, (rows - cam.cy) / cam.fy)
    d = np.tensordot(cam.rotation.T, np.stack([x, y, np.ones_like(x)]), axes=(1, 0))
    C = np.array(cam.position) - np.array([E0, N0, 0.0])
    # ground: h = relief(x(h), y(h))
    h = np.full(x.shape, p.origin[2])
    for _ in range(6):
        t = (h - C[2]) / d[2]
        gx, gy = C[0] + t * d[0], C[1] + t * d[1]
        h = g.relief(gx, gy)
    t_ground = (h - C[2]) / d[2]
    a = g.albedo(C[0] + t_ground * d[0], C[1] + t_ground * d[1])
    # pole: vertical cylinder (px, py, radius), from its foot to its top
    px, py = g.pole_xy
    top = float(g.pole_top())
    foot = float(g.relief(np.array(px), np.array(py)))
    t_top = (top - C[2]) / d[2]
    on_top = np.hypot(C[0] + t_top * d[0] - px, C[1] + t_top * d[1] - py) <= p.pole_radius
    ox, oy = C[0] - px, C[1] - py
    qa = d[0] ** 2 + d[1] ** 2
    qb = 2 * (ox * d[0] + oy * d[1])
    qc = ox * ox + oy * oy - p.pole_radius**2
    disc = qb * qb - 4 * qa * qc
    with np.errstate(invalid="ignore"):
        t_side = (-qb - np.sqrt(disc)) / (2 * qa)
    z_side = C[2] + t_side * d[2]
    on_side = (disc >= 0) & (z_side <= top) & (z_side >= foot) & (t_side < t_ground)
    a = np.where(on_side, 0.35, a)
    a = np.where(on_top, 1.0, a)
    return a


def _radial_blur(img: np.ndarray, cam: FrameCamera, centre: float, edge: float) -> np.ndarray:
    """Gaussian blur whose sigma grows with the squared radial distance:
    per pixel, linear interpolation between images blurred at 5 sigmas."""
    rows, cols = img.shape
    rr, cc = np.meshgrid(np.arange(rows) + 0.5, np.arange(cols) + 0.5, indexing="ij")
    r = np.hypot(rr - cam.cy, cc - cam.cx)
    rmax = math.hypot(max(cam.cy, rows - cam.cy), max(cam.cx, cols - cam.cx))
    sigma = centre + (edge - centre) * (r / rmax) ** 2
    levels = np.linspace(centre, edge, 5)
    stack = np.stack([ndimage.gaussian_filter(img, s, mode="nearest") for s in levels])
    pos = np.clip((sigma - centre) / max(edge - centre, 1e-9) * (len(levels) - 1), 0, len(levels) - 1 - 1e-9)
    i = np.floor(pos).astype(int)
    w = pos - i
    rsel, csel = np.indices(img.shape)
    return (1 - w) * stack[i, rsel, csel] + w * stack[i + 1, rsel, csel]


def _flight(p: UAVParams, rng: np.random.Generator) -> list[tuple[float, float, float]]:
    """(east, north, heading) of each frame centre, local metres: serpentine
    lines over the ROI, the ROI kept inside every frame, sub-pixel jitter."""
    side = p.roi * p.hr_gsd
    fx = p.cols * p.lr_gsd
    fy = p.rows * p.lr_gsd
    ax = max(0.0, (fx - side) / 2 - 4 * p.lr_gsd)  # frame-centre excursion keeping the ROI inside
    ay = max(0.0, (fy - side) / 2 - 4 * p.lr_gsd)
    lines = max(2, int(round(math.sqrt(p.frames * ay / max(ax, 1e-9))))) if ay > 0 else 1
    lines = min(lines, p.frames)
    per = [p.frames // lines + (1 if k < p.frames % lines else 0) for k in range(lines)]
    out = []
    for k, n in enumerate(per):
        y = -ay + (2 * ay * k / (lines - 1) if lines > 1 else ay)
        xs = np.linspace(-ax, ax, n) if n > 1 else np.zeros(1)
        heading = 90.0 if k % 2 == 0 else 270.0
        if k % 2:
            xs = xs[::-1]
        for x in xs:
            j = rng.uniform(-0.5, 0.5, 2) * p.lr_gsd
            out.append((float(x + j[0]), float(y + j[1]), heading))
    return out


def make_uav_scene(params: UAVParams = UAVParams(), out_dir: str | Path | None = None) -> UAVScene:
    """Render the synthetic UAV block (module docstring). With ``out_dir``
    also write ``frame_NN.tif`` (float32, no georeference), ``cameras.yaml``
    (nominal cameras), ``truth_ortho.tif`` and ``truth_dsm.tif``."""
    p = params
    rng = np.random.default_rng(p.seed + 1)
    g = _Ground(p)
    E0, N0, H0 = p.origin
    side = p.roi * p.hr_gsd
    grid = GroundGrid(p.crs, E0 - side / 2, N0 + side / 2, p.hr_gsd, p.roi, p.roi, p.roi)
    # truth: box average of the top view per HR cell
    s = p.truth_supersample
    sub = (np.arange(p.roi * s) + 0.5) / s
    X, Y = np.meshgrid(g.x0 + sub * p.hr_gsd, g.y0 - sub * p.hr_gsd)
    alb = g.albedo(X, Y)
    px, py = g.pole_xy
    alb = np.where(np.hypot(X - px, Y - py) <= p.pole_radius, 1.0, alb)
    truth = (p.dn_offset + p.dn_gain * alb).reshape(p.roi, s, p.roi, s).mean(axis=(1, 3)).astype(np.float32)
    cx, cy = np.meshgrid(g.x0 + (np.arange(p.roi) + 0.5) * p.hr_gsd, g.y0 - (np.arange(p.roi) + 0.5) * p.hr_gsd)
    dsm = g.relief(cx, cy)
    dsm = np.where(np.hypot(cx - px, cy - py) <= p.pole_radius, float(g.pole_top()), dsm).astype(np.float32)

    f = p.focal_px
    frames, cams, true_cams = [], [], []
    ss = p.supersample
    offs = (np.arange(ss) + 0.5) / ss
    rr, cc = np.meshgrid(np.arange(p.rows), np.arange(p.cols), indexing="ij")
    for k, (x, y, heading) in enumerate(_flight(p, rng)):
        true = FrameCamera(f, f, p.cols / 2, p.rows / 2, p.rows, p.cols, p.crs, (E0 + x, N0 + y, H0 + p.altitude),
                           rotation_nadir(heading), k1=-0.02, pixel_size_mm=p.pixel_size_mm, source=f"frame_{k:02d}")
        acc = np.zeros((p.rows, p.cols))
        for oy in offs:
            for ox in offs:
                acc += _render_rays(g, true, rr + oy, cc + ox)
        dn = p.dn_offset + p.dn_gain * acc / ss**2
        dn = _radial_blur(dn, true, p.blur_centre, p.blur_edge)
        dn = dn + rng.normal(0.0, p.noise, dn.shape)
        frames.append(dn.astype(np.float32))
        err = rng.normal(0.0, 1.0, 6)
        att = p.attitude_error_deg * err[3:]
        nominal = true.replace(
            position=tuple(np.array(true.position) + p.position_error * err[:3]),
            rotation=rotation_nadir(heading + att[0], att[1], att[2]),
        )
        cams.append(nominal)
        true_cams.append(true)
    chart = [(k, r0, r1, c0, c1) for k, r0, r1, c0, c1 in g.chart]
    pole = (g.pole_rc[0], g.pole_rc[1], p.pole_radius / p.hr_gsd)
    scene = UAVScene(frames, cams, true_cams, grid, truth, dsm, chart, pole, p)
    if out_dir is not None:
        scene.paths.update(write_uav_scene(scene, out_dir))
    return scene


def write_uav_scene(scene: UAVScene, out_dir: str | Path) -> dict:
    """Write a scene's frames, nominal cameras and truth (see
    :func:`make_uav_scene`); returns the paths."""
    import rasterio

    from tiledsm.io import atomic_path
    from tiledsm.ortho.cameras import write_cameras_yaml

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict = {"frames": []}
    for k, img in enumerate(scene.frames):
        pth = out / f"frame_{k:02d}.tif"
        with atomic_path(pth) as tmp:
            with rasterio.open(tmp, "w", driver="GTiff", width=img.shape[1], height=img.shape[0], count=1,
                               dtype="float32") as ds:
                ds.write(img, 1)
        paths["frames"].append(pth)
    paths["cameras"] = write_cameras_yaml(out / "cameras.yaml",
                                          {p.name: c for p, c in zip(paths["frames"], scene.cameras)})
    g = scene.grid
    for name, arr in (("truth_ortho", scene.truth), ("truth_dsm", scene.dsm)):
        pth = out / f"{name}.tif"
        with atomic_path(pth) as tmp:
            with rasterio.open(tmp, "w", driver="GTiff", width=g.width, height=g.height, count=1, dtype="float32",
                               crs=g.crs, transform=g.transform) as ds:
                ds.write(arr.astype(np.float32), 1)
        paths[name] = pth
    return paths
