"""The parameters of SGVLL matching (:class:`SGVLLParams`), apart from the
kernels: a recipe, a command's options and a plan validate them without
importing numba, OpenCV or the compiled kernels (:mod:`tiledsm.match.sgvll`),
which a validator imports only to check a ``kernel`` or ``device`` named
other than the defaults."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator

from tiledsm.spec import StrictModel, not_below, option, registered

__all__ = ["SGVLLParams"]


def _kernels() -> dict:
    """The registry of matching kernels (:data:`tiledsm.match.kernels.KERNELS`)."""
    from tiledsm.match.kernels import KERNELS

    return KERNELS


class SGVLLParams(StrictModel):
    """Parameters of :func:`match_block`.

    Attributes
    ----------
    window : int
        ZNCC window side on the ground grid, cells (odd).
    P1, P2 : float
        SGM penalties in cost units (cost = 1 - ZNCC, 0..2) for a change of
        one height step / more than one step between path neighbours.
        P1 0.3 lowers the real pair's NMAD and RMSE for little completeness
        (docs: decisions/speckle-slope.md, which gives the measurements).
    step_px : float
        Height step expressed in parallax: one step moves the projections
        of the best-separated view pair apart by about ``step_px`` pixels.
    zncc_min : float
        Cells whose winning (unaggregated) ZNCC is below this are NaN.
        0.25 is the lowest value that keeps the real pair's cells off by
        more than 10 m within 0.01 % (docs: decisions/zncc-min.md).
    ratio_max : float
        Cells whose aggregated peak ratio ``S_best / S_second`` exceeds this
        (ambiguous minimum) are NaN.
    reject_edges : bool
        NaN where the winner is the first or last candidate of the cell's
        range (the true height is probably outside it).
    speckle_size : int
        Connected components of fewer cells than this are removed
        (:meth:`speckle_max_diff` says which neighbours are connected);
        150 cells is above the largest blunder patch of the real pair
        (docs: decisions/speckle-slope.md).
    speckle_slope : float
        Neighbours are connected when the slope between them is at most
        this, degrees: a blunder patch meets the terrain around it in a
        step steeper than any hillside, whereas a 45 degree hillside stays
        one component (docs: decisions/speckle-slope.md).
    speckle_steps : float
        ... but never less than this many height steps (the sub-step
        noise of a flat area must not split it).
    proj_stride : int
        Projections are computed exactly every ``proj_stride`` cells and on
        a height lattice every ``lattice_steps`` steps, then interpolated
        (bilinear in x/y, linear in h).
    lattice_steps : int
        See ``proj_stride``.
    interpolation : str
        Image resampling: ``"linear"`` or ``"cubic"`` (OpenCV remap).
    invalid_cost : float
        Cost used for candidates without a valid ZNCC (nodata, flat).
    max_candidates : int
        Refuse blocks needing more candidates per cell than this.
    ref_sigma : float
        Smoothing (cells) of the reference surface built from per-cell
        bounds when no ``h_ref`` is given (see :func:`match_block`).
    weight_pairs : bool
        With three or more views, weight each pair's ZNCC by its squared
        parallax per metre of height (inverse variance; see
        :func:`tiledsm.match.cost.mean_zncc_cost`); ``False``: plain mean.
        Weighted, a third view at half the base keeps the NMAD of two wide
        views better than a plain mean (docs: guides/dsm.md, two vs three
        views; ``benchmarks/views.py``).
    kernel : str
        Implementation of the sweep and aggregation (:data:`~tiledsm.match.kernels.KERNELS`):
        ``"fast"`` (:mod:`tiledsm.match.sweep`: compiled candidate loop,
        only the candidates each cell needs), ``"reference"`` (the plain
        per-height sweep it is tested against) or ``"cuda"``
        (:mod:`tiledsm.match.cuda_kernel`: the fast kernel's arithmetic as
        compiled CUDA kernels, the volume kept on the GPU; the same
        heights bit for bit).
    device : str
        Where the ``"cuda"`` kernel runs: ``"cuda"``, ``"cuda:1"``...,
        several GPUs ``"cuda:0,1"`` or ``"cuda:all"`` (each matching thread
        keeps one of them; :func:`tiledsm.match.cuda_kernel.thread_device`)
        (``tiledsm dsm --device``); the other kernels run on the CPU
        (``"cpu"``).
    path_period : int
        Semi-global paths restart every ``path_period`` cells on lines of
        the whole grid (:func:`tiledsm.match.sgm.aggregate`): each cell's
        result depends only on cells within this distance, so tiles with
        this halo are exact; 0 = paths never restart (tiles then differ
        slightly near their borders).
    """

    window: int = Field(5, ge=1, description="ZNCC window side on the ground grid, cells (odd)")
    P1: float = Field(0.3, ge=0, description="SGM penalty for a change of one height step, cost units (1 - ZNCC)")
    P2: float = Field(2.0, validate_default=True,  # checked against a P1 given alone too
                     description="SGM penalty for a change of more than one step, cost units (>= P1)")
    step_px: float = Field(0.5, gt=0, description="height step as parallax of the best-separated view pair, pixels")
    zncc_min: float = Field(0.25, description="cells whose winning (unaggregated) ZNCC is below this are NaN")
    ratio_max: float = Field(0.98, description="cells whose aggregated peak ratio S_best / S_second exceeds this "
                             "(ambiguous minimum) are NaN")
    reject_edges: bool = Field(True, description="NaN where the winner is the first or last candidate of the cell")
    speckle_size: int = Field(150, ge=0, description="connected components of fewer cells than this are removed")
    speckle_slope: float = Field(60.0, gt=0, lt=90, description="neighbours are connected when the slope between "
                                 "them is at most this, degrees")
    speckle_steps: float = Field(0.5, description="... but never less than this many height steps")
    proj_stride: int = Field(8, ge=1, description="projections computed exactly every this many cells, "
                             "interpolated between")
    lattice_steps: int = Field(16, ge=1, description="projections computed exactly every this many height steps, "
                               "interpolated between")
    interpolation: Literal["linear", "cubic"] = Field("cubic", description="image resampling (OpenCV remap)")
    invalid_cost: float = Field(1.0, description="cost of a candidate without a valid ZNCC (nodata, flat), cost units")
    max_candidates: int = Field(2048, description="refuse blocks needing more candidates per cell than this")
    ref_sigma: float = Field(3.0, description="smoothing of the reference surface built from per-cell bounds, cells")
    weight_pairs: bool = Field(True, description="with three or more views, weight each pair's ZNCC by its squared "
                               "parallax per metre of height; false: plain mean")
    path_period: int = Field(64, ge=0, description="semi-global paths restart every this many cells (0: never), "
                             "which makes tiles exact with this halo")
    kernel: str = Field("fast", description="implementation of the sweep and aggregation: fast, reference or cuda")
    device: str = Field("cpu", description="where the cuda kernel runs: cuda, cuda:N, several GPUs cuda:N,M,... "
                        "or cuda:all; the others run on the cpu",
                        json_schema_extra=option("--device"))

    @model_validator(mode="before")
    @classmethod
    def _known_names(cls, data: object) -> object:
        """A misspelled parameter is named with the valid ones (issue 13)."""
        unknown = [k for k in data if k not in cls.model_fields] if isinstance(data, dict) else []
        if unknown:
            raise ValueError(f"unknown matching parameter(s) {', '.join(map(repr, unknown))}; "
                             f"valid: {', '.join(cls.model_fields)}")
        return data

    @field_validator("window")
    @classmethod
    def _odd_window(cls, value: int) -> int:
        if value % 2 == 0:
            raise ValueError(f"must be odd (a window has a centre cell), got {value}")
        return value

    _p2_above_p1 = field_validator("P2")(not_below("P1"))

    _known_kernel = field_validator("kernel")(registered(_kernels, "matching kernel"))

    @field_validator("device")
    @classmethod
    def _kernel_runs_there(cls, value: str, info: ValidationInfo) -> str:
        kernel = info.data.get("kernel")  # absent when the kernel itself was refused
        if value != "cpu" and kernel is not None:
            kernels = _kernels()
            if not kernels[kernel].on_device:
                raise ValueError(f"{value!r}: the {kernel!r} kernel runs on the CPU only")
            kernels[kernel].check_device(value)
        return value

    def speckle_max_diff(self, cell: float, step: float) -> float:
        """Largest height difference, metres, between connected neighbours
        of ``cell`` metres apart on a lattice of ``step`` metres (see
        ``speckle_slope``)."""
        return max(cell * math.tan(math.radians(self.speckle_slope)), self.speckle_steps * step)
