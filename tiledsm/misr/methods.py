"""SR-S, SR-R and SR-O: super-resolved orthoimages from many LR images.

The methods of the UAV multi-image SR paper, on an HR ground grid whose
cells are the LR GSD divided by ``scale``:

- **SR-S**: the reference image alone, orthorectified onto the HR grid with
  a cubic convolution (CR or CS);
- **SR-R**: every selected image orthorectified onto the HR grid (kernel
  NN/BL/CR/CS), registered to the reference ortho (sub-pixel translation
  by ECC, folded into its camera so each ortho is resampled once; grey
  levels adjusted by a linear fit), then averaged (NaN-aware);
- **SR-O**: iterative back projection (:mod:`tiledsm.misr.ibp`) of the same
  images' LR pixels, placed on the HR grid by their camera, the DSM and the
  SR-R registration, starting from the SR-R average.

The **reference** image is the one that sees the region nearest its
principal point; **radial selection** keeps the images in which the
region's centre lies within ``R`` (millimetres on the focal plane) of the
principal point.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import xarray as xr

from tiledsm.errors import TiledsmError
from tiledsm.geometry.camera import GroundShifted
from tiledsm.geometry.grid import GroundGrid
from tiledsm.misr.ibp import PSF, Observations, ibp
from tiledsm.misr.register import Registration, register
from tiledsm.ortho.recipe import OrthoSpec
from tiledsm.ortho.rectify import ImageSource, orthorectify

__all__ = ["MISRError", "SRInputs", "reference_index", "radial_select", "ortho_hr", "sr_s", "sr_r", "sr_o",
           "observations"]


class MISRError(TiledsmError):
    """Raised when a multi-image SR method cannot run (too few images, no
    image seeing the region); the message names the parameter."""


class RegistrationError(MISRError):
    """Fewer than 2 images could be registered to the reference ortho: the
    result would be one image, not multi-image SR."""


@dataclass(frozen=True, eq=False)
class SRInputs:
    """What every method needs.

    Attributes
    ----------
    frames : list of (rows, cols) arrays
        LR images, DN.
    cameras : list
        Their cameras (frame cameras: radial selection needs
        ``focal_plane_radius``).
    grid : GroundGrid
        HR grid (``chunk`` = tile side of every tiled step).
    dsm : (H, W) array
        Heights on ``grid``, the cameras' datum.
    scale : int
        LR GSD / HR cell.
    occlusion : bool
        Orthos mask hidden cells.
    """

    frames: list
    cameras: list
    grid: GroundGrid
    dsm: np.ndarray
    scale: int
    occlusion: bool = True
    #: orthos and registrations already computed, by (kernel, image) (shared by the methods)
    cache: dict = field(default_factory=dict, repr=False)

    def dsm_array(self) -> xr.DataArray:
        import rioxarray  # noqa: F401

        g = self.grid
        a = xr.DataArray(np.asarray(self.dsm, np.float64), dims=("y", "x"), coords=g.coords(), name="height")
        return a.rio.write_crs(g.crs).rio.write_transform(g.transform).chunk(g.chunk)


def _centre(inputs: SRInputs) -> tuple[np.ndarray, np.ndarray, float]:
    from tiledsm.geometry.footprint import to_lonlat

    g = inputs.grid
    lon, lat = to_lonlat(g.crs, np.array(np.mean(g.x)), np.array(np.mean(g.y)))
    return lon, lat, float(np.nanmedian(inputs.dsm))


def _radii(inputs: SRInputs) -> np.ndarray:
    lon, lat, h = _centre(inputs)
    out = []
    for cam in inputs.cameras:
        r, c = cam.project(lon, lat, h)
        out.append(float(cam.focal_plane_radius(r, c)) if hasattr(cam, "focal_plane_radius") else np.nan)
    return np.array(out)


def reference_index(inputs: SRInputs) -> int:
    """The image seeing the region's centre nearest its principal point."""
    r = _radii(inputs)
    if not np.isfinite(r).any():
        raise MISRError("reference: no camera gives a focal-plane radius (frame cameras needed)")
    return int(np.nanargmin(r))


def radial_select(inputs: SRInputs, radius: float | None) -> list[int]:
    """Images whose focal-plane radius of the region's centre is <= ``radius``
    (mm when the cameras know their pixel size, else pixels); all when None."""
    if radius is None:
        return list(range(len(inputs.frames)))
    r = _radii(inputs)
    return [i for i in range(len(r)) if r[i] <= radius]


def ortho_hr(inputs: SRInputs, index: int, kernel: str, camera=None) -> np.ndarray:
    """Ortho of image ``index`` on the HR grid (tiled, :func:`orthorectify`),
    through ``camera`` (default: the image's)."""
    cam = camera if camera is not None else inputs.cameras[index]
    src = ImageSource.from_array(inputs.frames[index], cam, name=f"image {index}")
    o = orthorectify(src, inputs.dsm_array(), OrthoSpec(kernel=kernel, occlusion=inputs.occlusion),
                     chunk=inputs.grid.chunk)
    return o.values


def sr_s(inputs: SRInputs, kernel: str = "cs") -> tuple[np.ndarray, dict]:
    """SR-S: the reference image's ortho on the HR grid."""
    ref = reference_index(inputs)
    return ortho_hr(inputs, ref, kernel), {"reference": ref, "images": 1}


def _need_two(indices, method: str) -> None:
    if len(indices) < 2:
        raise MISRError(f"{method}: needs at least 2 images, got {len(indices)} (check images / radial selection)")


def _registered(inputs: SRInputs, indices, kernel: str) -> tuple[list[np.ndarray], dict[int, Registration], int]:
    ref = reference_index(inputs)
    if ref not in indices:
        indices = [ref, *indices]
    orthos, regs = [], {}
    for i in sorted(set(indices), key=lambda k: (k != ref, k)):
        key = (kernel, i)
        if key not in inputs.cache:
            inputs.cache[key] = _register_one(inputs, i, ref, kernel)
        ortho, reg = inputs.cache[key]
        if reg is not None:
            orthos.append(ortho)
            regs[i] = reg
    if len(orthos) < 2:
        raise RegistrationError(
            f"only {len(orthos)} of {len(set(indices))} images registered to the reference ortho (image {ref}) by ECC: "
            "multi-image SR needs at least 2 (check the DSM, the cameras and the overlap)"
        )
    return orthos, regs, ref


def _register_one(inputs: SRInputs, i: int, ref: int, kernel: str) -> tuple[np.ndarray, Registration | None]:
    """Registered, grey-adjusted ortho of image ``i`` (None when ECC fails)."""
    if i == ref:
        return ortho_hr(inputs, ref, kernel), Registration()
    ref_ortho = inputs.cache[(kernel, ref)][0]
    reg = register(ortho_hr(inputs, i, kernel), ref_ortho)
    if not np.isfinite(reg.ecc):
        return None, None
    res = inputs.grid.resolution
    cam = GroundShifted(inputs.cameras[i], inputs.grid.crs, reg.tx * res, -reg.ty * res)
    return reg.gain * ortho_hr(inputs, i, kernel, camera=cam) + reg.offset, reg


def sr_r(inputs: SRInputs, kernel: str = "cs", indices=None) -> tuple[np.ndarray, dict]:
    """SR-R: registered, grey-adjusted orthos averaged (NaN-aware)."""
    indices = list(range(len(inputs.frames))) if indices is None else list(indices)
    _need_two(indices, "SR-R")
    orthos, regs, ref = _registered(inputs, indices, kernel)
    mean = _nanmean(orthos)
    return mean.astype(np.float32), {"reference": ref, "images": len(orthos), "registrations": {
        int(k): {"ty": r.ty, "tx": r.tx, "gain": r.gain, "offset": r.offset, "ecc": r.ecc} for k, r in regs.items()}}


def _nanmean(orthos: list[np.ndarray]) -> np.ndarray:
    """Cell-wise mean of the finite values (NaN where none)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN cells
        return np.nanmean(np.stack(orthos), axis=0)


def observations(inputs: SRInputs, regs: dict[int, Registration]) -> Observations:
    """LR pixels of the registered images on the HR grid: each pixel centre's
    ray meets the DSM (fixed-point iterations from the median height), its
    position is moved by the image's registration and its grey level
    adjusted; pixels landing outside the HR grid are dropped."""
    from scipy.ndimage import map_coordinates

    g = inputs.grid
    res = g.resolution
    h0 = float(np.nanmedian(inputs.dsm))
    dsm = np.where(np.isfinite(inputs.dsm), inputs.dsm, h0)
    us, vs, cs, ims = [], [], [], []
    for k, (i, reg) in enumerate(sorted(regs.items())):
        cam = inputs.cameras[i]
        img = np.asarray(inputs.frames[i], np.float64)
        rows, cols = np.meshgrid(np.arange(img.shape[0]) + 0.5, np.arange(img.shape[1]) + 0.5, indexing="ij")
        h = np.full(rows.shape, h0)
        for _ in range(6):
            e, n = cam.localize_xyz(rows, cols, h)
            u, v = (e - g.x0) / res, (g.y0 - n) / res
            h = map_coordinates(dsm, [v - 0.5, u - 0.5], order=1, mode="nearest")
        u, v = u - reg.tx, v - reg.ty
        keep = (u >= 0) & (u < g.width) & (v >= 0) & (v < g.height) & np.isfinite(img)
        us.append(u[keep])
        vs.append(v[keep])
        cs.append(reg.gain * img[keep] + reg.offset)
        ims.append(np.full(int(keep.sum()), k, np.int64))
    return Observations(np.concatenate(us), np.concatenate(vs), np.concatenate(cs), np.concatenate(ims))


def sr_o(
    inputs: SRInputs,
    psf: PSF = PSF(),
    kernel: str = "cs",
    indices=None,
    *,
    max_iter: int = 20,
    te: float = 0.0,
) -> tuple[np.ndarray, dict]:
    """SR-O: IBP from the SR-R average (module docstring); the report holds
    the iterations used and ``E(t)``."""
    indices = list(range(len(inputs.frames))) if indices is None else list(indices)
    _need_two(indices, "SR-O")
    orthos, regs, ref = _registered(inputs, indices, kernel)
    init = _nanmean(orthos)
    init = np.where(np.isfinite(init), init, np.nanmean(init))
    obs = observations(inputs, regs)
    f, rep = ibp(init, obs, psf, inputs.scale, chunk=inputs.grid.chunk, max_iter=max_iter, te=te)
    rep.update(reference=ref, images=len(regs), observations=int(obs.u.size))
    return f, rep
