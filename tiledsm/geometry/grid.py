"""Ground grids: the regular, north-up, projected grids DSMs live on.

Conventions
-----------
- A grid is north-up with square cells of ``resolution`` metres (CRS units).
  ``(x0, y0)`` is the **outer corner** of the top-left cell (west edge,
  north edge); the centre of cell ``[i, j]`` is at
  ``(x0 + (j + 0.5) * res, y0 - (i + 0.5) * res)``. This is GDAL's
  geotransform convention, so :attr:`GroundGrid.transform` maps
  ``(col, row)`` with corners at integers, exactly like an image.
- Row ``i`` grows southward (``y`` decreasing), column ``j`` eastward.
- ``bounds`` are ``(left, bottom, right, top)`` outer edges, rasterio order.
- Chunks are square ``chunk x chunk`` cells; the last row/column of chunks
  holds the remainder.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Iterator, Sequence

import numpy as np
from affine import Affine
from pyproj import CRS
from pyproj.exceptions import CRSError

from tiledsm.errors import GridError

__all__ = ["GroundGrid", "utm_crs", "check_height_range", "DEFAULT_CHUNK"]

#: default chunk edge, cells
DEFAULT_CHUNK = 512

# relative tolerance used when snapping bounds to multiples of the resolution,
# so that bounds already on the lattice are not pushed out by rounding noise
_SNAP_EPS = 1e-9


def _chunk_sizes(n: int, chunk: int) -> tuple[int, ...]:
    full, rest = divmod(n, chunk)
    return (chunk,) * full + ((rest,) if rest else ())


@dataclass(frozen=True)
class GroundGrid:
    """A north-up regular grid in a projected CRS.

    Parameters
    ----------
    crs : str
        Any CRS string pyproj understands (``"EPSG:32740"``, WKT, PROJ).
    x0, y0 : float
        West and north outer edges of the grid, CRS units (metres).
    resolution : float
        Cell edge, CRS units (metres), > 0.
    width, height : int
        Number of columns and rows, > 0.
    chunk : int
        Chunk edge in cells for dask and zarr, > 0.

    Raises
    ------
    GridError
        Non-positive or non-finite resolution, empty shape, bad chunk or a
        CRS pyproj cannot parse.
    """

    crs: str
    x0: float
    y0: float
    resolution: float
    width: int
    height: int
    chunk: int = DEFAULT_CHUNK

    def __post_init__(self) -> None:
        res = float(self.resolution)
        if not math.isfinite(res) or res <= 0:
            raise GridError(f"ground grid: resolution must be a positive number of metres, got {self.resolution!r}")
        for name in ("x0", "y0"):
            v = float(getattr(self, name))
            if not math.isfinite(v):
                raise GridError(f"ground grid: {name} must be finite, got {v!r}")
            object.__setattr__(self, name, v)
        for name in ("width", "height", "chunk"):
            v = getattr(self, name)
            if int(v) != v or int(v) <= 0:
                raise GridError(f"ground grid: {name} must be a positive integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        object.__setattr__(self, "resolution", res)
        try:
            crs = CRS.from_user_input(self.crs)
        except CRSError as exc:
            raise GridError(f"ground grid: unknown CRS {self.crs!r} ({exc})") from exc
        if crs.is_geographic:
            raise GridError(
                f"ground grid: CRS {self.crs!r} is geographic; DSM grids need a projected CRS in metres (e.g. UTM)"
            )
        object.__setattr__(self, "crs", str(self.crs))

    # ------------------------------------------------------------ geometry
    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)`` in cells."""
        return (self.height, self.width)

    @property
    def x(self) -> np.ndarray:
        """Cell-centre eastings, shape ``(width,)``, increasing."""
        return self.x0 + (np.arange(self.width) + 0.5) * self.resolution

    @property
    def y(self) -> np.ndarray:
        """Cell-centre northings, shape ``(height,)``, decreasing."""
        return self.y0 - (np.arange(self.height) + 0.5) * self.resolution

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """Outer edges ``(left, bottom, right, top)``, CRS units."""
        return (
            self.x0,
            self.y0 - self.height * self.resolution,
            self.x0 + self.width * self.resolution,
            self.y0,
        )

    @property
    def transform(self) -> Affine:
        """GDAL/rasterio geotransform: ``(col, row)`` corners -> ``(x, y)``."""
        return Affine(self.resolution, 0.0, self.x0, 0.0, -self.resolution, self.y0)

    @property
    def chunks(self) -> tuple[tuple[int, ...], tuple[int, ...]]:
        """Dask chunk sizes ``(row chunks, column chunks)``."""
        return (_chunk_sizes(self.height, self.chunk), _chunk_sizes(self.width, self.chunk))

    @property
    def numblocks(self) -> tuple[int, int]:
        """Number of chunks along rows and columns."""
        return (-(-self.height // self.chunk), -(-self.width // self.chunk))

    def block_window(self, i: int, j: int) -> tuple[int, int, int, int]:
        """Half-open cell window ``(row0, row1, col0, col1)`` of chunk ``(i, j)``."""
        nby, nbx = self.numblocks
        if not (0 <= i < nby and 0 <= j < nbx):
            raise GridError(f"ground grid: block ({i}, {j}) outside the {nby}x{nbx} block layout")
        c = self.chunk
        return (i * c, min((i + 1) * c, self.height), j * c, min((j + 1) * c, self.width))

    def blocks(self) -> Iterator[tuple[tuple[int, int], tuple[int, int, int, int]]]:
        """Iterate ``((i, j), (row0, row1, col0, col1))`` over all chunks, row-major."""
        nby, nbx = self.numblocks
        for i in range(nby):
            for j in range(nbx):
                yield (i, j), self.block_window(i, j)

    def subgrid(self, row0: int, row1: int, col0: int, col1: int) -> "GroundGrid":
        """The grid of cells ``[row0:row1, col0:col1]`` (half-open, same CRS,
        resolution and chunk). Indices may lie outside this grid (the
        sub-grid then extends it, e.g. for a halo), but must be non-empty."""
        row0, row1, col0, col1 = (int(v) for v in (row0, row1, col0, col1))
        if row1 <= row0 or col1 <= col0:
            raise GridError(f"ground grid: empty window rows {row0}:{row1}, cols {col0}:{col1}")
        return replace(
            self,
            x0=self.x0 + col0 * self.resolution,
            y0=self.y0 - row0 * self.resolution,
            width=col1 - col0,
            height=row1 - row0,
        )

    #: alias of :meth:`subgrid`
    window = subgrid

    def coords(self) -> dict[str, np.ndarray]:
        """``{"y": ..., "x": ...}`` cell-centre coordinates for xarray."""
        return {"y": self.y, "x": self.x}

    # ------------------------------------------------------- constructors
    @classmethod
    def from_bounds(
        cls,
        crs: str,
        bounds: Sequence[float],
        resolution: float,
        chunk: int = DEFAULT_CHUNK,
    ) -> "GroundGrid":
        """Smallest grid whose edges are multiples of ``resolution`` and
        which covers ``bounds``.

        Parameters
        ----------
        crs : str
            Projected CRS.
        bounds : (left, bottom, right, top)
            CRS units; snapped **outward** to multiples of ``resolution``
            (so independent runs at the same resolution share one lattice).
        resolution : float
            Cell edge, metres.
        chunk : int
            Chunk edge, cells.
        """
        res = float(resolution)
        if not math.isfinite(res) or res <= 0:
            raise GridError(f"ground grid: resolution must be a positive number of metres, got {resolution!r}")
        try:
            left, bottom, right, top = (float(b) for b in bounds)
        except (TypeError, ValueError) as exc:
            raise GridError(f"ground grid: bounds must be (left, bottom, right, top), got {bounds!r}") from exc
        if not all(math.isfinite(v) for v in (left, bottom, right, top)):
            raise GridError(f"ground grid: bounds must be finite, got {tuple(bounds)!r}")
        if not (right > left and top > bottom):
            raise GridError(f"ground grid: empty bounds (left, bottom, right, top) = {tuple(bounds)!r}")
        c0 = math.floor(left / res + _SNAP_EPS)
        c1 = math.ceil(right / res - _SNAP_EPS)
        r0 = math.floor(bottom / res + _SNAP_EPS)
        r1 = math.ceil(top / res - _SNAP_EPS)
        return cls(crs, c0 * res, r1 * res, res, max(c1 - c0, 1), max(r1 - r0, 1), chunk)

    @classmethod
    def from_transform(cls, crs, transform, shape: tuple[int, int], chunk: int | None = None,
                       name: str = "grid") -> "GroundGrid":
        """The grid of a raster given by its CRS, affine geotransform
        (GDAL order, top-left corner of the top-left cell) and ``(rows,
        cols)`` shape; ``name`` names the raster in errors. Reading that
        from a file or a DataArray is :func:`tiledsm.io.grids.grid_like`'s.

        Raises
        ------
        GridError
            No CRS, a rotated or non-square pixel grid, or a south-up grid.
        """
        if crs is None:
            raise GridError(f"{name}: has no CRS; cannot align a ground grid to it")
        a, b, c, d, e, f = tuple(transform)[:6]
        if b != 0 or d != 0:
            raise GridError(f"{name}: rotated geotransform {tuple(transform)[:6]} is not supported")
        if e >= 0:
            raise GridError(f"{name}: geotransform is not north-up (e = {e})")
        if not math.isclose(a, -e, rel_tol=1e-9):
            raise GridError(f"{name}: non-square cells ({a} x {-e}) are not supported")
        crs_str = crs.to_string() if hasattr(crs, "to_string") else str(crs)
        return cls(crs_str, c, f, a, int(shape[1]), int(shape[0]), chunk or DEFAULT_CHUNK)


def utm_crs(lon: float, lat: float) -> str:
    """The WGS84 / UTM zone CRS containing a point.

    Standard 6-degree zones (``zone = floor((lon + 180) / 6) + 1``), north
    (EPSG:326zz) for ``lat >= 0`` else south (EPSG:327zz); the Norway and
    Svalbard exceptions of the MGRS are not applied.

    Parameters
    ----------
    lon, lat : float
        Degrees; longitude is wrapped into [-180, 180).

    Returns
    -------
    str
        ``"EPSG:326zz"`` or ``"EPSG:327zz"``.
    """
    lon, lat = float(lon), float(lat)
    if not (math.isfinite(lon) and math.isfinite(lat)) or abs(lat) > 90:
        raise GridError(f"utm_crs: invalid position lon={lon}, lat={lat}")
    lon = (lon + 180.0) % 360.0 - 180.0
    zone = min(int(math.floor((lon + 180.0) / 6.0)) + 1, 60)
    code = (32600 if lat >= 0 else 32700) + zone
    return f"EPSG:{code}"


def check_height_range(h_range) -> tuple[float, float]:
    """``(hmin, hmax)`` as floats (ellipsoidal metres), finite and ordered;
    :class:`~tiledsm.errors.GridError` otherwise."""
    try:
        hmin, hmax = (float(h) for h in h_range)
    except (TypeError, ValueError) as exc:
        raise GridError(f"height range must be (hmin, hmax) in metres, got {h_range!r}") from exc
    if not (math.isfinite(hmin) and math.isfinite(hmax)) or hmin > hmax:
        raise GridError(f"height range must be finite with hmin <= hmax, got {h_range!r}")
    return hmin, hmax
