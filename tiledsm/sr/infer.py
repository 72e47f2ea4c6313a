"""Tiled super-resolution of a scene: one dask ``map_overlap`` call.

Conventions
-----------
- Input: a scene ``xr.DataArray`` with dims ``(y, x)`` or ``(band, y, x)``,
  digital numbers (any dtype), NaN for nodata. Each band is super-resolved
  on its own (the networks are single-band).
- Values are divided by ``value_scale`` (the sensor's full scale,
  ``2**bit_depth - 1``) before the network and multiplied back after;
  the output is float32 in the input's units.
- Output pixel ``[i, j]`` covers input area ``[i/s, (i+1)/s) x [j/s,
  (j+1)/s)`` (corner convention, GDAL's), so the output RPC is
  ``rpc.scaled(s)`` and a 1-D coordinate ``c`` with step ``d`` becomes
  ``c0 - d/2 + (k + 0.5) d / s``.
- Nodata: NaN input pixels are set to 0 (normalised) before the network,
  and output pixels whose input pixel (nearest neighbour) is NaN are NaN.
  The fill is a constant, so tiling stays exact; valid pixels within the
  model's halo of nodata are influenced by the fill.
- Tiling: halo = the model's receptive field (``model.halo`` LR pixels),
  ``boundary="none"`` so the image edges get the model's own reflect
  padding exactly as in a whole-image call; blocks are trimmed by
  ``scale * halo`` on their inner sides. Result equals
  :func:`sr_array` on the whole image (to float32 round-off).
"""

from __future__ import annotations

from typing import Sequence

import dask.array as da
import numpy as np
import torch
import xarray as xr
from torch import nn

from tiledsm.sr.models.base import SRModel
from tiledsm.sr.models.srmd import check_blur
from tiledsm.sr.registry import SRError, load_pretrained

__all__ = ["sr_array", "super_resolve", "resolve_model", "value_scale_for", "BIT_DEPTHS"]

#: bit depths tried (smallest first) when the full scale must be inferred
BIT_DEPTHS = (8, 10, 11, 12, 14, 16)


def resolve_model(model: str | nn.Module, scale: int, device: str = "cpu") -> SRModel:
    """A model instance for ``scale``: a registry name (shipped weights) or a module."""
    if isinstance(model, str):
        return load_pretrained(model, scale, device=device)
    if not isinstance(model, SRModel):
        raise SRError(f"model must be a registry name or a tiledsm SRModel, got {type(model).__name__}")
    if model.scale != scale:
        raise SRError(f"{type(model).__name__} is built for scale x{model.scale}, asked for x{scale}")
    return model.to(device).eval()


def _degradation_kwargs(model: SRModel, blur_sigma: float | None, noise: float | None, value_scale: float) -> dict:
    if not model.takes_degradation:
        if blur_sigma is not None or noise is not None:
            raise SRError(f"{type(model).__name__} takes no degradation parameters (blur_sigma, noise); only SRMD does")
        return {}
    if blur_sigma is None:
        raise SRError(f"{type(model).__name__} needs blur_sigma (Gaussian sigma of the LR blur, HR pixels, or 'bicubic')")
    try:
        blur = check_blur(blur_sigma)
    except ValueError as exc:
        raise SRError(str(exc)) from None
    if noise is not None and noise < 0:
        raise SRError(f"noise must be >= 0, got {noise}")
    return {"blur_sigma": blur, "noise": float(noise or 0.0) / value_scale}


def sr_array(
    image: np.ndarray,
    model: SRModel,
    *,
    value_scale: float = 1.0,
    device: str = "cpu",
    blur_sigma: float | str | None = None,
    noise: float | None = None,
) -> np.ndarray:
    """Super-resolve one 2-D image in one network call (the in-memory kernel).

    Parameters
    ----------
    image : numpy.ndarray
        ``(h, w)`` digital numbers, NaN for nodata.
    model : SRModel
        Network (eval mode) with ``model.scale = s``.
    value_scale : float
        Full scale used to normalise to [0, 1].
    device : str
        Torch device (``"cpu"``, ``"cuda"``).
    blur_sigma, noise : float, optional
        SRMD only: blur sigma (HR pixels, or ``"bicubic"``) and noise std
        (digital numbers).

    Returns
    -------
    numpy.ndarray
        ``(h * s, w * s)`` float32, NaN where the covering input pixel is NaN.
    """
    kwargs = _degradation_kwargs(model, blur_sigma, noise, value_scale)
    img = np.asarray(image, dtype=np.float32)
    nan = np.isnan(img)
    x = np.where(nan, np.float32(0), img / np.float32(value_scale))
    t = torch.from_numpy(np.ascontiguousarray(x))[None, None].to(device)
    with torch.no_grad():
        y = model(t, **kwargs)[0, 0].float().cpu().numpy() * np.float32(value_scale)
    if nan.any():
        s = model.scale
        y[np.repeat(np.repeat(nan, s, axis=0), s, axis=1)] = np.nan
    return y.astype(np.float32, copy=False)


def _sr_block(block, *, model, halo, value_scale, device, degradation, block_info=None):
    """Task body: SR of one overlapped block, trimmed of its scaled halo."""
    info = block_info[0]
    loc, nchunks = info["chunk-location"], info["num-chunks"]
    s = model.scale
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        if block.ndim == 2:
            out = sr_array(block, model, value_scale=value_scale, device=device, **degradation)
        else:
            out = np.stack([sr_array(b, model, value_scale=value_scale, device=device, **degradation) for b in block])
    finally:
        torch.set_num_threads(threads)
    # boundary="none": the first/last block of an axis has no outer halo
    index = [slice(None)] * out.ndim
    for ax in (out.ndim - 2, out.ndim - 1):
        lo = halo * s if loc[ax] > 0 else 0
        hi = halo * s if loc[ax] < nchunks[ax] - 1 else 0
        index[ax] = slice(lo, out.shape[ax] - hi)
    return out[tuple(index)]


def _merge_small_chunks(chunks: Sequence[int], minimum: int) -> tuple[int, ...]:
    """Merge chunks smaller than ``minimum`` into a neighbour (dask needs halo <= chunk)."""
    out = list(chunks)
    i = 0
    while len(out) > 1 and i < len(out):
        if out[i] < minimum:
            j = i - 1 if i == len(out) - 1 else i + 1
            out[min(i, j)] = out[i] + out[j]
            del out[max(i, j)]
            i = 0
            continue
        i += 1
    return tuple(out)


def value_scale_for(scene: xr.DataArray) -> float:
    """Full scale of a scene's digital numbers.

    In order: ``attrs["value_scale"]``; ``2**attrs["bit_depth"] - 1``;
    ``255`` for uint8 data; otherwise the smallest ``2**b - 1`` (b in
    :data:`BIT_DEPTHS`) not below the data's maximum (one pass over the
    data), or the maximum itself above 16 bits.
    """
    attrs = scene.attrs
    if "value_scale" in attrs:
        return float(attrs["value_scale"])
    if "bit_depth" in attrs:
        return float(2 ** int(attrs["bit_depth"]) - 1)
    if scene.dtype == np.uint8:
        return 255.0
    vmax = float(scene.max(skipna=True).values)
    if not np.isfinite(vmax) or vmax <= 0:
        return 1.0
    for b in BIT_DEPTHS:
        if vmax <= 2**b - 1:
            return float(2**b - 1)
    return vmax


def _scaled_coord(c: np.ndarray, n_out: int, s: int) -> np.ndarray | None:
    c = np.asarray(c)
    if c.ndim != 1 or c.size < 2 or not np.issubdtype(c.dtype, np.number):
        return None
    step = (c[-1] - c[0]) / (c.size - 1)
    return c[0] - step / 2 + (np.arange(n_out) + 0.5) * step / s


def super_resolve(
    scene: xr.DataArray,
    model: str | nn.Module,
    scale: int,
    *,
    device: str = "cpu",
    blur_sigma: float | str | None = None,
    noise: float | None = None,
    value_scale: float | None = None,
    chunks: int | None = None,
) -> xr.DataArray:
    """Super-resolve a scene tile by tile (lazy).

    Parameters
    ----------
    scene : xarray.DataArray
        ``(y, x)`` or ``(band, y, x)``, numpy- or dask-backed, NaN = nodata.
        ``attrs["rpc"]`` (GDAL RPC dict), if present, is regenerated for the
        new grid.
    model : str or SRModel
        Registry name (``"bicubic"``, ``"srcnn"``, ``"vdsr"``, ``"srmd"``:
        shipped weights via :func:`~tiledsm.sr.registry.load_pretrained`)
        or a model instance with ``model.scale == scale``.
    scale : int
        Upscaling factor.
    device : str
        Torch device for the network (``"cpu"`` always works).
    blur_sigma : float or "bicubic", optional
        SRMD: Gaussian blur sigma of the LR image formation, HR pixels, or
        ``"bicubic"`` for LR images made by bicubic downsampling.
    noise : float, optional
        SRMD: noise standard deviation, digital numbers.
    value_scale : float, optional
        Full scale for normalisation (default: :func:`value_scale_for`).
    chunks : int, optional
        Rechunk the image axes to this size first (default: keep the
        scene's chunks; a numpy-backed scene becomes one chunk).

    Returns
    -------
    xarray.DataArray
        float32, ``scale`` times larger on ``y``/``x``, chunks scaled by
        ``scale``. ``attrs``: the scene's, with ``rpc`` replaced by
        ``RPC.scaled(scale)`` and ``sr_model``, ``sr_scale``,
        ``sr_value_scale`` (and ``sr_weights``, ``sr_blur_sigma``,
        ``sr_noise`` when relevant) added.
    """
    if scene.ndim not in (2, 3):
        raise SRError(f"super_resolve: scene must have dims (y, x) or (band, y, x), got {scene.dims}")
    net = resolve_model(model, scale, device)
    vscale = float(value_scale) if value_scale is not None else value_scale_for(scene)
    degradation = {"blur_sigma": blur_sigma, "noise": noise}
    _degradation_kwargs(net, blur_sigma, noise, vscale)  # validate early
    halo = net.halo
    data = scene.data
    if not isinstance(data, da.Array):
        data = da.from_array(np.asarray(data), chunks=-1)
    if chunks is not None:
        data = data.rechunk({data.ndim - 2: chunks, data.ndim - 1: chunks})
    new_chunks = list(data.chunks)
    for ax in (data.ndim - 2, data.ndim - 1):
        new_chunks[ax] = _merge_small_chunks(data.chunks[ax], halo)
    data = data.rechunk(tuple(new_chunks)).astype(np.float32)
    depth = {ax: 0 for ax in range(data.ndim)}
    depth.update({data.ndim - 2: halo, data.ndim - 1: halo})
    out_chunks = tuple(
        tuple(c * scale for c in ch) if ax >= data.ndim - 2 else ch for ax, ch in enumerate(data.chunks)
    )
    out = da.map_overlap(
        _sr_block,
        data,
        depth=depth,
        boundary="none",
        trim=False,
        chunks=out_chunks,
        dtype=np.float32,
        meta=np.empty((0,) * data.ndim, np.float32),
        model=net,
        halo=halo,
        value_scale=vscale,
        device=device,
        degradation=degradation,
    )
    coords = {}
    for dim in scene.dims:
        if dim not in scene.coords:
            continue
        if dim == scene.dims[-1] or dim == scene.dims[-2]:
            new = _scaled_coord(scene.coords[dim].values, out.shape[scene.dims.index(dim)], scale)
            if new is not None:
                coords[dim] = new
        else:
            coords[dim] = scene.coords[dim]
    attrs = dict(scene.attrs)
    if "rpc" in attrs:
        from tiledsm.geometry import RPC

        attrs["rpc"] = RPC.from_gdal(attrs["rpc"]).scaled(scale).to_gdal()
    model_name = model if isinstance(model, str) else type(net).__name__.lower()
    attrs.update(sr_model=model_name, sr_scale=int(scale), sr_value_scale=vscale)
    if getattr(net, "weights_file", None):
        attrs["sr_weights"] = net.weights_file.rsplit("/", 1)[-1]
    if net.takes_degradation:
        attrs.update(sr_blur_sigma=check_blur(blur_sigma), sr_noise=float(noise or 0.0))
    result = xr.DataArray(out, dims=scene.dims, coords=coords, attrs=attrs, name=scene.name)
    return _scaled_georeference(scene, result, scale)


def _scaled_georeference(scene: xr.DataArray, result: xr.DataArray, scale: int) -> xr.DataArray:
    """Carry a CRS and its transform (pixel size / ``scale``) for georeferenced scenes."""
    try:
        crs = scene.rio.crs
    except Exception:  # no rioxarray accessor or no spatial dims
        return result
    if crs is None:
        return result
    from affine import Affine

    return result.rio.write_crs(crs).rio.write_transform(scene.rio.transform() @ Affine.scale(1.0 / scale))
