"""Rational polynomial camera (RPC00B, third order, 80 coefficients).

Conventions
-----------
- Pixel coordinates are GDAL's: ``(row, col)`` with the **top-left corner of
  the image at (0, 0)**, so the centre of array element ``[i, j]`` is at
  ``(i + 0.5, j + 0.5)``. They equal the raw RPC formula's line/sample
  plus 0.5 (the RPC standard puts the first pixel's *centre* at 0).
- Ground coordinates are WGS84 longitude/latitude in degrees and heights in
  metres above the WGS84 ellipsoid.
- Every method broadcasts over numpy arrays of any shape.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Mapping

import numba as nb
import numpy as np

from tiledsm.errors import RPCError

__all__ = ["RPC", "rpc_terms"]

# GDAL metadata keys of the scalar normalisation parameters, in field order.
_SCALAR_KEYS = {
    "line_off": "LINE_OFF",
    "samp_off": "SAMP_OFF",
    "lat_off": "LAT_OFF",
    "lon_off": "LONG_OFF",
    "height_off": "HEIGHT_OFF",
    "line_scale": "LINE_SCALE",
    "samp_scale": "SAMP_SCALE",
    "lat_scale": "LAT_SCALE",
    "lon_scale": "LONG_SCALE",
    "height_scale": "HEIGHT_SCALE",
}
_COEFF_KEYS = {
    "line_num": "LINE_NUM_COEFF",
    "line_den": "LINE_DEN_COEFF",
    "samp_num": "SAMP_NUM_COEFF",
    "samp_den": "SAMP_DEN_COEFF",
}


def rpc_terms(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The 20 RPC00B monomials of normalised (lon, lat, height).

    Parameters
    ----------
    x, y, z : array_like
        Normalised longitude (L), latitude (P) and height (H).

    Returns
    -------
    numpy.ndarray
        Shape ``(20,) + broadcast shape``, in RPC00B order:
        1, L, P, H, LP, LH, PH, L², P², H², PLH, L³, LP², LH², L²P, P³, PH²,
        L²H, P²H, H³.
    """
    x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
    one = np.ones_like(x)
    return np.stack(
        [
            one, x, y, z, x * y, x * z, y * z, x * x, y * y, z * z,
            x * y * z, x ** 3, x * y * y, x * z * z, x * x * y, y ** 3,
            y * z * z, x * x * z, y * y * z, z ** 3,
        ]
    )


# IEEE division: a denominator that crosses zero (far outside the model's
# domain) gives inf or NaN, as numpy's form did, not ZeroDivisionError
@nb.njit(nogil=True, cache=True, error_model="numpy")
def _rational(x, y, z, line_num, line_den, samp_num, samp_den, ln, sn):
    """``ln[k], sn[k]``: the two RPC ratios at normalised ground point
    ``k`` of the flat arrays ``x, y, z`` (the monomials of
    :func:`rpc_terms`, formed once per point and never stored: a point
    costs about a hundred flops, where the stacked ``(20, n)`` terms of
    :func:`rpc_terms` cost memory traffic)."""
    t = np.empty(20)
    for k in range(x.shape[0]):
        L = x[k]
        P = y[k]
        H = z[k]
        t[0] = 1.0
        t[1] = L
        t[2] = P
        t[3] = H
        t[4] = L * P
        t[5] = L * H
        t[6] = P * H
        t[7] = L * L
        t[8] = P * P
        t[9] = H * H
        t[10] = L * P * H
        t[11] = L * L * L
        t[12] = L * P * P
        t[13] = L * H * H
        t[14] = L * L * P
        t[15] = P * P * P
        t[16] = P * H * H
        t[17] = L * L * H
        t[18] = P * P * H
        t[19] = H * H * H
        a = 0.0
        b = 0.0
        c = 0.0
        d = 0.0
        for m in range(20):
            a += line_num[m] * t[m]
            b += line_den[m] * t[m]
            c += samp_num[m] * t[m]
            d += samp_den[m] * t[m]
        ln[k] = a / b
        sn[k] = c / d


@dataclass(frozen=True, eq=False)
class RPC:
    """A third-order RPC camera (GDAL/RPC00B layout).

    Attributes are the normalisation offsets/scales (pixels, degrees,
    metres) and the four 20-term coefficient vectors. ``line_off`` and
    ``samp_off`` follow the RPC standard (first pixel *centre* at 0); the
    methods translate to GDAL's corner convention (see module docstring).
    """

    line_off: float
    samp_off: float
    lat_off: float
    lon_off: float
    height_off: float
    line_scale: float
    samp_scale: float
    lat_scale: float
    lon_scale: float
    height_scale: float
    line_num: np.ndarray
    line_den: np.ndarray
    samp_num: np.ndarray
    samp_den: np.ndarray
    #: where the model came from (file path and format), for reports only
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        where = f" ({self.source})" if self.source else ""
        for name in _COEFF_KEYS:
            arr = np.asarray(getattr(self, name), dtype=float).ravel()
            if arr.size != 20:
                raise RPCError(f"RPC{where}: {name} has {arr.size} coefficients, expected 20")
            if not np.all(np.isfinite(arr)):
                raise RPCError(f"RPC{where}: {name} has non-finite coefficients")
            object.__setattr__(self, name, arr)
        for name in _SCALAR_KEYS:
            v = float(getattr(self, name))
            if not np.isfinite(v):
                raise RPCError(f"RPC{where}: {name} is not finite")
            object.__setattr__(self, name, v)
        for name in ("line_scale", "samp_scale", "lat_scale", "lon_scale", "height_scale"):
            if getattr(self, name) == 0:
                raise RPCError(f"RPC{where}: {name} is zero")
        for name in ("line_num", "samp_num"):
            if not np.any(getattr(self, name)):
                # GDAL reads a coefficient list shorter than 20 as zeros
                raise RPCError(f"RPC{where}: {name} is all zeros (a truncated coefficient list? 20 are needed)")
        if self.line_den[0] == 0 and not np.any(self.line_den):
            raise RPCError(f"RPC{where}: line_den is all zeros")
        if self.samp_den[0] == 0 and not np.any(self.samp_den):
            raise RPCError(f"RPC{where}: samp_den is all zeros")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RPC):
            return NotImplemented
        return all(
            np.array_equal(getattr(self, f.name), getattr(other, f.name))
            for f in dataclasses.fields(self)
            if f.compare
        )

    # ------------------------------------------------------------------ GDAL
    @classmethod
    def from_gdal(cls, md: Mapping[str, object], source: str = "") -> "RPC":
        """Build from GDAL's RPC metadata domain (``LINE_OFF``, ...,
        ``SAMP_DEN_COEFF``; coefficient values as space-separated strings or
        sequences). Keys are case-insensitive."""
        upper = {str(k).upper(): v for k, v in md.items()}
        where = f" in {source}" if source else ""
        kwargs: dict[str, object] = {}
        for name, key in {**_SCALAR_KEYS, **_COEFF_KEYS}.items():
            if key not in upper:
                raise RPCError(f"RPC{where}: missing {key}")
            value = upper[key]
            try:
                if name in _COEFF_KEYS:
                    if isinstance(value, str):
                        value = [float(t) for t in value.replace(",", " ").split()]
                    kwargs[name] = np.asarray(value, dtype=float)
                else:
                    kwargs[name] = float(str(value).split()[0]) if isinstance(value, str) else float(value)
            except (TypeError, ValueError) as exc:
                raise RPCError(f"RPC{where}: {key} is not numeric ({value!r})") from exc
        return cls(**kwargs, source=source)  # type: ignore[arg-type]

    def to_gdal(self) -> dict[str, str]:
        """GDAL RPC metadata dict (strings), as written in TIFF tags."""
        md = {key: repr(float(getattr(self, name))) for name, key in _SCALAR_KEYS.items()}
        for name, key in _COEFF_KEYS.items():
            md[key] = " ".join(repr(float(c)) for c in getattr(self, name))
        return md

    # ------------------------------------------------------------ projection
    def _normalise_ground(self, lon, lat, h):
        x = (np.asarray(lon, float) - self.lon_off) / self.lon_scale
        y = (np.asarray(lat, float) - self.lat_off) / self.lat_scale
        z = (np.asarray(h, float) - self.height_off) / self.height_scale
        return x, y, z

    def _project_normalised(self, x, y, z):
        x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float), np.asarray(z, float))
        ln = np.empty(x.shape)
        sn = np.empty(x.shape)
        _rational(np.ravel(x), np.ravel(y), np.ravel(z), self.line_num, self.line_den, self.samp_num,
                  self.samp_den, ln.reshape(-1), sn.reshape(-1))
        return ln, sn

    def project(self, lon, lat, h) -> tuple[np.ndarray, np.ndarray]:
        """Project ground points to the image.

        Parameters
        ----------
        lon, lat : array_like
            WGS84 longitude and latitude, degrees.
        h : array_like
            Height above the WGS84 ellipsoid, metres.

        Returns
        -------
        row, col : numpy.ndarray
            Pixel coordinates, GDAL convention (top-left image corner at
            (0, 0); pixel ``[i, j]`` has its centre at ``(i+.5, j+.5)``).
        """
        ln, sn = self._project_normalised(*self._normalise_ground(lon, lat, h))
        row = ln * self.line_scale + self.line_off + 0.5
        col = sn * self.samp_scale + self.samp_off + 0.5
        return row, col

    def localize(
        self, row, col, h, *, tol: float = 1e-8, max_iter: int = 30
    ) -> tuple[np.ndarray, np.ndarray]:
        """Ground position of image points at given ellipsoidal heights.

        Inverts :meth:`project` by Newton iterations in normalised
        coordinates (analytic-free: a central-difference Jacobian), starting
        from the scene centre.

        Parameters
        ----------
        row, col : array_like
            Pixel coordinates, GDAL convention (see :meth:`project`).
        h : array_like
            Heights above the WGS84 ellipsoid, metres.
        tol : float
            Convergence threshold on the pixel residual, pixels.
        max_iter : int
            Iteration cap; points not converged by then raise
            :class:`~tiledsm.errors.RPCError`.

        Returns
        -------
        lon, lat : numpy.ndarray
            Degrees.
        """
        row, col, h = np.broadcast_arrays(
            np.asarray(row, float), np.asarray(col, float), np.asarray(h, float)
        )
        ln_t = (row - 0.5 - self.line_off) / self.line_scale
        sn_t = (col - 0.5 - self.samp_off) / self.samp_scale
        z = (h - self.height_off) / self.height_scale
        x = np.zeros_like(ln_t)
        y = np.zeros_like(ln_t)
        eps = 1e-6
        pix_scale = max(abs(self.line_scale), abs(self.samp_scale))
        for _ in range(max_iter):
            l0, s0 = self._project_normalised(x, y, z)
            rl, rs = ln_t - l0, sn_t - s0
            if np.all(np.maximum(np.abs(rl), np.abs(rs)) * pix_scale < tol):
                break
            lx, sx = self._project_normalised(x + eps, y, z)
            ly, sy = self._project_normalised(x, y + eps, z)
            a, b = (lx - l0) / eps, (ly - l0) / eps
            c, d = (sx - s0) / eps, (sy - s0) / eps
            det = a * d - b * c
            with np.errstate(divide="ignore", invalid="ignore"):
                dx = (d * rl - b * rs) / det
                dy = (-c * rl + a * rs) / det
            x = x + dx
            y = y + dy
        else:
            l0, s0 = self._project_normalised(x, y, z)
            err = np.maximum(np.abs(ln_t - l0), np.abs(sn_t - s0)) * pix_scale
            if not np.all(err < max(tol, 1e-4)):
                where = f" of {self.source}" if self.source else ""
                raise RPCError(
                    f"RPC localisation{where} did not converge "
                    f"(max residual {np.nanmax(err):.3g} px after {max_iter} iterations)"
                )
        lon = x * self.lon_scale + self.lon_off
        lat = y * self.lat_scale + self.lat_off
        return lon, lat

    # --------------------------------------------------------- derived models
    def replace(self, **changes) -> "RPC":
        """A copy with some fields changed (``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)

    def scaled(self, s: float) -> "RPC":
        """Exact RPC of the image resampled by factor ``s``.

        GDAL convention on both sides: the image corner stays at (0, 0) and
        ``new (row, col) = s * old (row, col)`` (``s = 2``: twice as many
        pixels; ``s = 0.5``: half). Only ``line/samp_off`` and
        ``line/samp_scale`` change: ``off' = s * (off + .5) - .5``,
        ``scale' = s * scale``.
        """
        s = float(s)
        if not (np.isfinite(s) and s > 0):
            raise ValueError(f"RPC.scaled: factor must be finite and > 0, got {s}")
        return self.replace(
            line_off=s * (self.line_off + 0.5) - 0.5, samp_off=s * (self.samp_off + 0.5) - 0.5,
            line_scale=s * self.line_scale, samp_scale=s * self.samp_scale,
            source=f"{self.source} scaled x{s:g}" if self.source else f"scaled x{s:g}",
        )

    def cropped(self, row0: float, col0: float) -> "RPC":
        """Exact RPC of a crop whose top-left corner is pixel ``(row0, col0)``
        of this image: ``new (row, col) = old (row, col) - (row0, col0)``."""
        return self.replace(
            line_off=self.line_off - float(row0), samp_off=self.samp_off - float(col0),
            source=f"{self.source} cropped at ({row0:g}, {col0:g})" if self.source
            else f"cropped at ({row0:g}, {col0:g})",
        )

    def image_window(self) -> tuple[float, float, float, float]:
        """The RPC's own image normalisation box ``(row0, row1, col0, col1)``
        (GDAL convention): ``off + .5 ± scale``. Often, not always, the
        image extent (cropped RPCs keep the full image's ground scales)."""
        r, c = self.line_off + 0.5, self.samp_off + 0.5
        return (r - abs(self.line_scale), r + abs(self.line_scale),
                c - abs(self.samp_scale), c + abs(self.samp_scale))

    def ground_box(
        self,
        image_window: tuple[float, float, float, float],
        h_range: tuple[float, float],
        n: int = 9,
    ) -> tuple[tuple[float, float], tuple[float, float]]:
        """Lon/lat bounding box (degrees) of an image window
        ``(row0, row1, col0, col1)`` localised at the two heights of
        ``h_range`` (metres, ellipsoidal), from ``n`` points per window edge.
        """
        r0, r1, c0, c1 = image_window
        t = np.linspace(0.0, 1.0, n)
        rows = np.concatenate([r0 + (r1 - r0) * t, np.full(n, r1), r0 + (r1 - r0) * t, np.full(n, r0)])
        cols = np.concatenate([np.full(n, c0), c0 + (c1 - c0) * t, np.full(n, c1), c0 + (c1 - c0) * t])
        lon, lat = self.localize(rows[:, None], cols[:, None], np.asarray(h_range, float)[None, :])
        return (float(lon.min()), float(lon.max())), (float(lat.min()), float(lat.max()))
