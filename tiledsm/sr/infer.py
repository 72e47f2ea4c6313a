"""Tiled super-resolution of a scene: one dask ``map_overlap`` call.

Conventions
-----------
- Input: a scene ``xr.DataArray`` with dims ``(y, x)`` or ``(band, y, x)``,
  digital numbers (any dtype), NaN for nodata. Each band is super-resolved
  on its own (the networks are single-band).
- Values are divided by ``value_scale`` before the network and multiplied
  back after; the output is float32 in the input's units. The default
  normalisation, ``"stretch"``, takes ``value_scale`` as the scene's
  99.9th percentile (:func:`stretch_scale`): the networks were trained on
  images that fill [0, 1], and a 12-bit Pleiades scene divided by its
  full scale 4095 sits below 0.2, where every shipped network does worse
  than on the same image stretched (README, "Super-resolution before
  matching"). ``"full_scale"`` divides by ``2**bit_depth - 1``
  (:func:`value_scale_for`). The value is one number per scene, computed
  before tiling, so tiles stay exact.
- Output pixel ``[i, j]`` covers input area ``[i/s, (i+1)/s) x [j/s,
  (j+1)/s)`` (corner convention, GDAL's), so the output RPC is
  ``rpc.scaled(s)`` and a 1-D coordinate ``c`` with step ``d`` becomes
  ``c0 - d/2 + (k + 0.5) d / s``.
- Nodata: NaN input pixels are set to 0 (normalised) before the network,
  and output pixels whose input pixel (nearest neighbour) is NaN are NaN.
  The fill is a constant, so tiling stays exact; valid pixels within the
  model's halo of nodata are influenced by the fill.
- Values outside [0, 1] after normalisation are not clipped away: the
  network gets the image clipped to [0, 1] and the rest is upsampled
  bicubically and added (:func:`sr_array`).
- Tiling: halo = the model's receptive field (``model.halo`` LR pixels,
  at least the bicubic kernel's 2),
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
from tiledsm.sr.models.bicubic import Bicubic
from tiledsm.sr.models.srmd import check_blur
from tiledsm.sr.registry import SRError, chain_scheme, load_pretrained, weight_chain

__all__ = [
    "sr_array", "super_resolve", "resolve_model", "value_scale_for", "stretch_scale", "NORMALISATIONS",
    "BIT_DEPTHS", "STRETCH_PERCENTILE",
]

#: bit depths tried (smallest first) when the full scale must be inferred
BIT_DEPTHS = (8, 10, 11, 12, 14, 16)
#: percentile of a scene's valid pixels that the "stretch" normalisation maps to 1
STRETCH_PERCENTILE = 99.9
#: histogram bins over [0, full scale] for :func:`stretch_scale` (1/16 DN at 12 bit)
_STRETCH_BINS = 65536


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
        Value mapped to 1. The network gets the normalised image clipped
        to [0, 1]; the part outside is upsampled bicubically and added.
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
    # The network sees its training range [0, 1]; what lies outside (the
    # brightest 0.1 % of a stretched scene) is carried past it by bicubic
    # interpolation, which is linear, so nothing is clipped away. The
    # published SRMD loses 0.9 dB on the s2p pair when fed values above 1.
    inside = np.clip(x, 0, 1)
    t = torch.from_numpy(np.ascontiguousarray(inside))[None, None].to(device)
    with torch.no_grad():
        y = model(t, **kwargs)[0, 0].float()
        if not np.array_equal(inside, x):
            excess = torch.from_numpy(np.ascontiguousarray(x - inside))[None, None].to(device)
            y = y + Bicubic(model.scale)(excess)[0, 0].float()
        y = y.cpu().numpy() * np.float32(value_scale)
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


def stretch_scale(scene: xr.DataArray, percentile: float = STRETCH_PERCENTILE) -> float:
    """The scene value mapped to 1 by the ``"stretch"`` normalisation.

    The ``percentile`` of the valid (non-NaN) pixels in ``[0, full scale]``
    (full scale from :func:`value_scale_for`), from one streaming histogram
    of 65536 bins over the scene's chunks (precision: full scale / 65536,
    the upper edge of the bin that holds the percentile). A percentile
    rather than the maximum: a few saturated or specular pixels (the
    ``s2p_pair`` image: maximum 1883 DN, 99.9th percentile 545 DN) would
    otherwise keep the scene dark. Falls back to the full scale for a scene
    whose percentile lies in the first bin (e.g. all zero).
    """
    if not 0 < percentile <= 100:
        raise SRError(f"stretch percentile must be in (0, 100], got {percentile}")
    full = value_scale_for(scene)
    data = scene.data
    if not isinstance(data, da.Array):
        data = da.from_array(np.asarray(data), chunks=-1)
    data = data.astype(np.float32)
    counts, edges = da.histogram(da.where(da.isnan(data), -1, data), bins=_STRETCH_BINS, range=(0.0, full))
    counts = np.asarray(counts.compute(), np.int64)
    total = int(counts.sum())
    if total == 0:
        return full
    k = int(np.searchsorted(np.cumsum(counts), percentile / 100.0 * total))
    if k == 0:  # (almost) nothing above zero: nothing to stretch
        return full
    return float(edges[min(k + 1, _STRETCH_BINS)])


#: how digital numbers are brought to the [0, 1] range the networks were trained on: name -> value_scale(scene)
NORMALISATIONS = {"stretch": stretch_scale, "full_scale": value_scale_for}


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
    normalisation: str = "stretch",
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
        Scene value mapped to 1 before the network (replaces
        ``normalisation``).
    normalisation : {"stretch", "full_scale"}
        How ``value_scale`` is found when not given (:data:`NORMALISATIONS`):
        the scene's 99.9th percentile (default) or its full scale
        ``2**bit_depth - 1``.
    chunks : int, optional
        Rechunk the image axes to this size first (default: keep the
        scene's chunks; a numpy-backed scene becomes one chunk).

    Returns
    -------
    xarray.DataArray
        float32, ``scale`` times larger on ``y``/``x``, chunks scaled by
        ``scale``. ``attrs``: the scene's, with ``rpc`` replaced by
        ``RPC.scaled(scale)`` and ``sr_model``, ``sr_scale``,
        ``sr_value_scale``, ``sr_normalisation`` (and ``sr_weights``, ``sr_blur_sigma``,
        ``sr_noise`` when relevant) added.
    """
    if scene.ndim not in (2, 3):
        raise SRError(f"super_resolve: scene must have dims (y, x) or (band, y, x), got {scene.dims}")
    chain = weight_chain(model, scale) if isinstance(model, str) else None
    if chain is not None and len(chain) > 1:
        return _super_resolve_chain(scene, model, chain, device=device, blur_sigma=blur_sigma, noise=noise,
                                    value_scale=value_scale, normalisation=normalisation, chunks=chunks)
    net = resolve_model(model, scale, device)
    if normalisation not in NORMALISATIONS:
        raise SRError(f"normalisation must be one of {sorted(NORMALISATIONS)}, got {normalisation!r}")
    if value_scale is not None:
        vscale, normalisation = float(value_scale), "given"
    else:
        vscale = NORMALISATIONS[normalisation](scene)
    degradation = {"blur_sigma": blur_sigma, "noise": noise}
    _degradation_kwargs(net, blur_sigma, noise, vscale)  # validate early
    halo = max(net.halo, Bicubic(scale).halo)  # the carried excess is interpolated bicubically
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
    attrs.update(sr_model=model_name, sr_scale=int(scale), sr_value_scale=vscale,
                 sr_normalisation=normalisation)
    if getattr(net, "weights_file", None):
        attrs["sr_weights"] = net.weights_file.rsplit("/", 1)[-1]
    if net.takes_degradation:
        attrs.update(sr_blur_sigma=check_blur(blur_sigma), sr_noise=float(noise or 0.0))
    result = xr.DataArray(out, dims=scene.dims, coords=coords, attrs=attrs, name=scene.name)
    return _scaled_georeference(scene, result, scale)


def _super_resolve_chain(scene: xr.DataArray, model: str, chain: tuple[int, ...], *, chunks: int | None,
                         value_scale: float | None, normalisation: str, **kw) -> xr.DataArray:
    """:func:`super_resolve` by a network without native weights for the
    product of ``chain``: its shipped weights applied once per factor
    (:func:`tiledsm.sr.registry.weight_chain`), a stated substitute. Every
    pass divides by the first pass's ``value_scale``; later passes are
    rechunked to the first pass's input tile so a tile's memory does not
    grow with each pass. The RPC and geotransform compose exactly
    (``RPC.scaled(a).scaled(b) == RPC.scaled(a * b)``). ``attrs`` gain
    ``sr_scheme`` (e.g. ``"x2 applied 2 times"``); ``sr_scale`` is the total."""
    if chunks is None and isinstance(scene.data, da.Array):
        chunks = int(scene.data.chunks[-1][0])
    out = super_resolve(scene, model, chain[0], value_scale=value_scale, normalisation=normalisation,
                        chunks=chunks, **kw)
    first = dict(out.attrs)
    for s in chain[1:]:
        out = super_resolve(out, model, s, value_scale=first["sr_value_scale"], chunks=chunks, **kw)
    out.attrs.update(sr_scale=int(np.prod(chain)), sr_normalisation=first["sr_normalisation"],
                     sr_scheme=chain_scheme(chain))
    return out


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
