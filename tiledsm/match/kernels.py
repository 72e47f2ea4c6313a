"""The registry of SGVLL matching kernels: implementations of the heavy
steps of :func:`tiledsm.match.sgvll.match_block` (cost volume and
semi-global aggregation), chosen by :attr:`SGVLLParams.kernel
<tiledsm.match.params.SGVLLParams>`, and the three built in: ``"fast"``
(:mod:`tiledsm.match.sweep`), ``"reference"``
(:mod:`tiledsm.match.sweep_reference`) and ``"cuda"``
(:mod:`tiledsm.match.cuda_kernel`)."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable

__all__ = ["KERNELS", "MatchKernel", "register_kernel"]


@dataclass(frozen=True)
class MatchKernel:
    """One implementation of the SGVLL kernel's heavy steps.

    Attributes
    ----------
    cost_volume : callable
        ``(imgs, lat_r, lat_c, stride, k0, dh, href, step, origin, nodes0,
        win_r, win_c, cubic, base, nvalid, half, pair_w, details=None) ->
        vol`` (see :func:`tiledsm.match.sweep.cost_volume`).
    aggregate : callable
        Semi-global aggregation, the signature of
        :func:`tiledsm.match.sgm.aggregate`.
    on_device : bool
        Both steps take a ``device=`` (:meth:`for_device`); the others run
        on the CPU only.
    best : callable, optional
        Aggregation and winner-take-all in one: ``aggregate``'s signature,
        returning :func:`~tiledsm.match.winner.winner_take_all`'s arrays
        against the volume (:func:`tiledsm.match.sgm.aggregate_best`);
        without it, :meth:`winners` runs the two in turn.
    check_device : callable, optional
        ``(device) -> None``, raising :class:`ValueError` naming a device
        the kernel cannot run on (kernels ``on_device``).
    """

    cost_volume: Callable
    aggregate: Callable
    on_device: bool = False
    best: Callable | None = None
    check_device: Callable | None = None

    def winners(self, vol, P1: float, P2: float, *, nvalid, **kwargs) -> tuple:
        """``(index, smin, ratio, cbest)`` of volume ``vol`` aggregated
        with ``aggregate``'s arguments."""
        if self.best is not None:
            return self.best(vol, P1, P2, nvalid=nvalid, **kwargs)
        from tiledsm.match.winner import winner_take_all

        return winner_take_all(self.aggregate(vol, P1, P2, nvalid=nvalid, **kwargs), vol, nvalid)

    def for_device(self, device: str) -> MatchKernel:
        """The kernel with its steps bound to ``device`` (itself when it
        runs on the CPU only)."""
        if not self.on_device:
            return self
        return MatchKernel(functools.partial(self.cost_volume, device=device),
                           functools.partial(self.aggregate, device=device),
                           best=None if self.best is None else functools.partial(self.best, device=device),
                           check_device=self.check_device)


#: matching kernels by name (:attr:`SGVLLParams.kernel`); see :func:`register_kernel`
KERNELS: dict[str, MatchKernel] = {}


def register_kernel(name: str, kernel: MatchKernel) -> None:
    """Add a kernel to :data:`KERNELS` (a name is taken once)."""
    if name in KERNELS:
        raise ValueError(f"matching kernel {name!r} is already registered")
    KERNELS[name] = kernel


def _register_builtin() -> None:
    # imported here, not at the top: the dataclass and the registry load
    # without numba; the implementations register once, on first import
    from tiledsm.match import cuda_kernel
    from tiledsm.match.sgm import aggregate, aggregate_best
    from tiledsm.match.sweep import cost_volume
    from tiledsm.match.sweep_reference import cost_volume_reference

    register_kernel("reference", MatchKernel(cost_volume_reference, aggregate))
    register_kernel("fast", MatchKernel(cost_volume, functools.partial(aggregate, fast=True), best=aggregate_best))
    register_kernel("cuda", MatchKernel(cuda_kernel.cost_volume, cuda_kernel.aggregate, on_device=True,
                                        best=cuda_kernel.best, check_device=cuda_kernel.check_device))


_register_builtin()
