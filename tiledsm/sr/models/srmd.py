"""SRMD of Zhang, Zuo & Zhang (2018), "Learning a single convolutional
super-resolution network for multiple degradations", CVPR,
doi:10.1109/CVPR.2018.00344.

Degradation model: ``LR = (HR * k)↓s + n`` with ``k`` a Gaussian blur
kernel, ``↓s`` direct downsampling (every ``s``-th pixel) and ``n`` white
Gaussian noise. The network takes the LR image plus ``t + 1`` constant
maps: the kernel projected on a ``t``-dimensional PCA basis and the noise
level. Besides Gaussians, the kernel may be the antialiased bicubic one
(``blur_sigma="bicubic"``, :data:`BICUBIC`): the degradation most LR
images of SR benchmarks (and of the SR -> DSM experiment) come from.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import nn

from tiledsm.sr.models._layers import BICUBIC_RADIUS, PaddedConv2d, bicubic_upsample, conv_radius
from tiledsm.sr.models.base import SRModel

__all__ = ["SRMD", "gaussian_kernel", "bicubic_kernel", "blur_kernel", "check_blur", "kernel_pca_basis", "KERNEL_SIZE", "BICUBIC"]

#: side of the blur kernels (HR pixels)
KERNEL_SIZE = 15

#: the ``blur_sigma`` that selects the antialiased bicubic kernel
BICUBIC = "bicubic"


def gaussian_kernel(sigma_x: float, sigma_y: float | None = None, theta: float = 0.0, size: int = KERNEL_SIZE) -> np.ndarray:
    """Normalised (sum 1) anisotropic Gaussian kernel, ``size x size``,
    centred on the middle pixel. Sigmas in HR pixels, ``theta`` in radians.
    ``sigma <= 0`` gives a delta kernel."""
    sigma_y = sigma_x if sigma_y is None else sigma_y
    if sigma_x <= 0 or sigma_y <= 0:
        k = np.zeros((size, size))
        k[size // 2, size // 2] = 1.0
        return k
    r = np.arange(size) - size // 2
    yy, xx = np.meshgrid(r, r, indexing="ij")
    c, s = np.cos(theta), np.sin(theta)
    u = c * xx + s * yy
    v = -s * xx + c * yy
    k = np.exp(-0.5 * ((u / sigma_x) ** 2 + (v / sigma_y) ** 2))
    return k / k.sum()


def bicubic_kernel(scale: int, size: int = KERNEL_SIZE) -> np.ndarray:
    """The antialiased bicubic downsampling kernel by ``scale`` (Keys,
    ``a = -0.5``, stretched by ``scale``: support ``4 scale`` HR px), ``size x
    size``, centred on the middle pixel, sum 1.

    As for the Gaussians, the half-pixel shift of sampling at LR pixel
    centres belongs to the sampler, not to the kernel: this is the kernel's
    shape, the one its degradation code describes. Its negative lobes are
    what a Gaussian cannot describe.
    """
    from tiledsm.sr.degradation import KERNELS  # the same Keys kernel that makes the sr_dsm LR pairs

    cubic, _ = KERNELS["bicubic"](scale, None)
    w = cubic(np.arange(size, dtype=float) - size // 2)
    k = np.outer(w, w)
    return k / k.sum()


def check_blur(blur_sigma: float | str) -> float | str:
    """``blur_sigma`` as SRMD takes it: :data:`BICUBIC`, or a sigma >= 0 in HR
    px (float). Raises ``ValueError`` naming what it got."""
    if isinstance(blur_sigma, str):
        if blur_sigma != BICUBIC:
            raise ValueError(f"blur_sigma must be a sigma in HR pixels or {BICUBIC!r}, got {blur_sigma!r}")
        return blur_sigma
    if not float(blur_sigma) >= 0:
        raise ValueError(f"blur_sigma must be >= 0, got {blur_sigma}")
    return float(blur_sigma)


def blur_kernel(blur_sigma: float | str, scale: int) -> np.ndarray:
    """The kernel a ``blur_sigma`` names: :func:`bicubic_kernel` for
    :data:`BICUBIC`, else an isotropic Gaussian of that sigma (HR px)."""
    blur = check_blur(blur_sigma)
    return bicubic_kernel(scale) if blur == BICUBIC else gaussian_kernel(blur)


@functools.lru_cache(maxsize=8)
def kernel_pca_basis(dim: int = 15, size: int = KERNEL_SIZE) -> np.ndarray:
    """PCA basis ``(dim, size * size)`` of a fixed family of kernels: Gaussians
    (isotropic and anisotropic, sigma 0.2-4 HR px, 8 orientations) and the
    bicubic kernels of scales 2, 3 and 4 (weighted as 20 Gaussians each, so
    that their negative lobes get a component of the code).

    The basis is stored in the model's state_dict, so shipped weights carry
    the basis they were trained with (SVD signs are library-dependent)."""
    kernels = []
    for sx in np.linspace(0.2, 4.0, 20):
        for sy in np.linspace(0.2, 4.0, 20):
            for th in np.linspace(0, np.pi, 8, endpoint=False):
                kernels.append(gaussian_kernel(sx, sy, th, size).ravel())
    for scale in (2, 3, 4):
        kernels += [bicubic_kernel(scale, size).ravel()] * 20
    a = np.asarray(kernels)
    _, _, vt = np.linalg.svd(a, full_matrices=False)
    basis = vt[:dim].copy()
    basis.flags.writeable = False  # cached: shared between calls
    return basis


class SRMD(SRModel):
    """SRMD network: ``layers`` 3x3 convolutions on the LR grid (ReLU after
    each but the last, batch norm in the middle ones), the last producing
    ``scale**2`` channels rearranged by pixel shuffle. Padding before each
    convolution (symmetric, as the method states, unless ``padding`` says
    otherwise).

    Parameters
    ----------
    scale : int
        Upscaling factor.
    layers : int
        Convolution layers (paper: 12).
    features : int
        Hidden channels (paper: 128).
    pca_dim : int
        Dimension ``t`` of the kernel code (paper: 15).
    residual : bool
        Add the bicubic upsampling of the LR image to the output (a global
        skip, as in VDSR; the paper has none: ``False``). The last layer
        then starts at zero, so the untrained network is exactly bicubic
        and a short training schedule only has to learn the missing detail.
    padding : str
        Padding before each convolution, one of
        :data:`~tiledsm.sr.models._layers.PAD_MODES`.

    Notes
    -----
    ``forward(x, blur_sigma, noise)``: ``blur_sigma`` is the isotropic
    Gaussian sigma in HR pixels, or :data:`BICUBIC`; ``noise`` is the noise
    standard deviation in normalised units (same scale as ``x``). Both may be
    given per batch item (a sequence or 1-D tensor of length ``N``).
    """

    takes_degradation = True

    def __init__(self, scale: int = 2, layers: int = 12, features: int = 128, pca_dim: int = 15, residual: bool = False, padding: str = "symmetric") -> None:
        super().__init__(scale)
        if layers < 2:
            raise ValueError(f"SRMD: layers must be >= 2, got {layers}")
        # torch.tensor copies: the cached basis is read-only (as_tensor warned)
        self.register_buffer("pca", torch.tensor(kernel_pca_basis(pca_dim), dtype=torch.float32))
        mods: list[nn.Module] = [PaddedConv2d(1 + pca_dim + 1, features, 3, pad_mode=padding), nn.ReLU(inplace=True)]
        for _ in range(layers - 2):
            mods += [PaddedConv2d(features, features, 3, bias=False, pad_mode=padding), nn.BatchNorm2d(features), nn.ReLU(inplace=True)]
        last = PaddedConv2d(features, self.scale**2, 3, pad_mode=padding)
        mods += [last, nn.PixelShuffle(self.scale)]
        self.body = nn.Sequential(*mods)
        self.residual = bool(residual)
        if self.residual:
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    @property
    def halo(self) -> int:
        # everything happens on the LR grid; pixel shuffle is local; the
        # bicubic skip has edge effects up to BICUBIC_RADIUS LR px
        r = conv_radius(self.body)
        return max(r, BICUBIC_RADIUS) if self.residual else r

    def degradation_code(self, blur_sigma: float | str, noise: float) -> torch.Tensor:
        """The ``t + 1`` degradation values (PCA code of the kernel, noise)."""
        k = torch.as_tensor(blur_kernel(blur_sigma, self.scale).ravel(), dtype=self.pca.dtype, device=self.pca.device)
        code = self.pca @ k
        return torch.cat([code, torch.as_tensor([float(noise)], dtype=code.dtype, device=code.device)])

    def forward(self, x: torch.Tensor, blur_sigma=1.0, noise=0.0) -> torch.Tensor:  # noqa: D102
        n, _, h, w = x.shape
        per_item = isinstance(blur_sigma, (list, tuple)) or (isinstance(blur_sigma, torch.Tensor) and blur_sigma.ndim == 1)
        if per_item:
            # one degradation per batch item (training)
            sig = blur_sigma.tolist() if isinstance(blur_sigma, torch.Tensor) else list(blur_sigma)
            nse = noise.tolist() if isinstance(noise, torch.Tensor) else list(noise)
            code = torch.stack([self.degradation_code(b, float(v)) for b, v in zip(sig, nse)])
        else:
            code = self.degradation_code(check_blur(blur_sigma), float(noise)).expand(n, -1)
        maps = code[:, :, None, None].expand(n, code.shape[1], h, w).to(x.dtype)
        out = self.body(torch.cat([x, maps], dim=1))
        return out + bicubic_upsample(x, self.scale) if self.residual else out
