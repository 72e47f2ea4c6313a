"""Where the step of a displacement field lies across a given fault trace (pure numpy)."""

from __future__ import annotations

import numpy as np

__all__ = ["locate_trace"]


def locate_trace(fields: dict, distance: np.ndarray, offsets: dict, fault, half_width: float, res: float) -> dict | None:
    """Where the step of the field lies across the trace: the signed
    distance ``d0`` whose step function best fits (least absolute misfit)
    the displacement projected on the offset's direction and scaled 0 (left
    block) .. 1 (right block), over cells within ``half_width`` metres.
    ``d0`` is the located trace's offset from the given one (metres,
    positive: to the right)."""
    o_a, o_c = offsets.get("along_strike"), offsets.get("across_strike")
    if o_a is None or o_c is None:
        return None
    vec = o_a["offset"] * fault.strike + o_c["offset"] * fault.normal  # (east, north) metres
    size = float(np.hypot(*vec))
    if size < 5 * res * 0.05:  # no step to locate (under 0.25 px)
        return None
    proj = (fields["dE"] * vec[0] + fields["dN"] * vec[1]) / size
    left = np.isfinite(proj) & (distance < -half_width / 2) & (distance > -half_width)
    if not left.any():
        return None
    u = (proj - np.median(proj[left])) / size
    use = np.isfinite(u) & (np.abs(distance) < half_width)
    d, v = distance[use], u[use]
    cand = np.arange(-half_width / 2, half_width / 2, res / 10)
    misfit = np.array([np.abs(v - (d >= c)).sum() for c in cand])
    # every position between the same two cells fits as well: the middle of the best ones, not the first
    d0 = float(np.mean(cand[misfit <= misfit.min() + 1e-9]))
    return {"offset_m": d0, "offset_px": d0 / res, "cells": int(use.sum())}
