"""Image-space bias models of the bias-compensated RPC (Fraser & Hanley
2003, PE&RS 69(1) 53-57), in one registry.

With ``(l, s)`` the measured row/column of a ground point (GDAL pixel
convention: the top-left image corner at (0, 0)) and ``(r, c)`` its RPC
projection::

    l + A0 + A1 * l + A2 * s = r
    s + B0 + B1 * l + B2 * s = c

A model is the subset of ``A0..B2`` that is estimated (the others are 0).
``A0``/``B0`` are pixels, the other terms dimensionless.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tiledsm.errors import InvalidOptionError

__all__ = ["BiasModel", "MODELS", "TERMS", "get_model", "choose_model"]

#: every term, in the order of ``(A0, A1, A2, B0, B1, B2)``
TERMS = ("A0", "A1", "A2", "B0", "B1", "B2")


@dataclass(frozen=True)
class BiasModel:
    """One bias model.

    Attributes
    ----------
    name : str
    terms : tuple of str
        Estimated terms (a subset of :data:`TERMS`, in that order).
    min_gcps : int
        GCP measurements an image needs for its absolute bias alone (the
        number of unknowns of one image equation, non-collinear points).
    """

    name: str
    terms: tuple[str, ...]
    min_gcps: int

    @property
    def size(self) -> int:
        return len(self.terms)

    def full(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(A0, A1, A2), (B0, B1, B2)`` of a parameter vector (zeros for
        terms the model does not estimate)."""
        v = dict(zip(TERMS, np.zeros(6)))
        v.update(zip(self.terms, np.asarray(x, float)))
        return np.array([v["A0"], v["A1"], v["A2"]]), np.array([v["B0"], v["B1"], v["B2"]])

    def correction(self, x: np.ndarray, l: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Left-hand sides ``(l + A0 + A1 l + A2 s, s + B0 + B1 l + B2 s)``."""
        a, b = self.full(x)
        return l + a[0] + a[1] * l + a[2] * s, s + b[0] + b[1] * l + b[2] * s

    def design(self, l: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Derivatives of the row and column left-hand sides with respect to
        the model's terms: two ``(n, size)`` arrays."""
        one = np.ones_like(l)
        zero = np.zeros_like(l)
        cols = {"A0": (one, zero), "A1": (l, zero), "A2": (s, zero),
                "B0": (zero, one), "B1": (zero, l), "B2": (zero, s)}
        dr = np.stack([cols[t][0] for t in self.terms], -1)
        dc = np.stack([cols[t][1] for t in self.terms], -1)
        return dr, dc


#: name -> model
MODELS: dict[str, BiasModel] = {}


def _register(model: BiasModel) -> None:
    if model.name in MODELS:
        raise ValueError(f"bias model {model.name!r} registered twice")
    MODELS[model.name] = model


_register(BiasModel("shift", ("A0", "B0"), 1))
_register(BiasModel("affine", TERMS, 3))


def get_model(name: str) -> BiasModel:
    """The model called ``name``; :class:`InvalidOptionError` listing the
    known ones otherwise."""
    try:
        return MODELS[name]
    except KeyError:
        raise InvalidOptionError(f"model: unknown bias model {name!r} (known: {', '.join(MODELS)})") from None


def choose_model(n_gcp: int, n_tie: int, min_tie_affine: int = 30) -> BiasModel:
    """The model for an image with ``n_gcp`` GCP and ``n_tie`` tie-point
    measurements: ``affine`` when the GCPs alone fix it (>= 3) or when tie
    points are many (>= ``min_tie_affine``: the linear terms are then fixed
    relative to the other images), else ``shift``."""
    if n_gcp >= MODELS["affine"].min_gcps or n_tie >= min_tie_affine:
        return MODELS["affine"]
    return MODELS["shift"]
