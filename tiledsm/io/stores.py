"""Zarr stores: products written whole (:func:`write_zarr`) or block by block with resume
(:func:`create_store`, :class:`ChunkStore`, :func:`write_blocks`, :func:`write_resumable`)."""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping, Sequence

import dask
import numpy as np
import rioxarray  # noqa: F401  (registers the .rio accessor)
import xarray as xr

from tiledsm.errors import GridError, InputFileError, TiledsmError
from tiledsm.io.atomic import commit_path, remove_path, atomic_path
from tiledsm.io.codecs import store_encoding
from tiledsm.io.opened import open_store_array
from tiledsm.io.scenes import open_scene

log = logging.getLogger("tiledsm.io")

#: dataset attribute naming the variable when a store holds one DataArray
_DA_ATTR = "tiledsm_dataarray"
#: xarray's placeholder name for an unnamed DataArray
_UNNAMED = "__xarray_dataarray_variable__"
#: dataset attribute describing a resumable store's layout
_STORE_ATTR = "tiledsm_store"
_PROGRESS = "_progress"


# --------------------------------------------------------------------------- zarr
def _clean_for_zarr(ds: xr.Dataset) -> xr.Dataset:
    ds = ds.copy()
    for v in ds.variables.values():
        keep = {k: v.encoding[k] for k in ("compressors", "filters", "write_empty_chunks") if k in v.encoding}
        v.encoding = keep
    return ds


def _as_dataset(obj) -> xr.Dataset:
    if isinstance(obj, xr.DataArray):
        name = obj.name if obj.name is not None else _UNNAMED
        ds = obj.to_dataset(name=name, promote_attrs=False)
        ds.attrs = {_DA_ATTR: name, **{k: obj.attrs[k] for k in ("fingerprint",) if k in obj.attrs}}  # the store's
        return ds
    if isinstance(obj, xr.Dataset):
        return obj
    raise TypeError(f"write_zarr: expected an xarray DataArray or Dataset, got {type(obj).__name__}")


def _uniform_chunks(ds: xr.Dataset) -> xr.Dataset:
    """Zarr needs equal chunks along each dim except the last one."""
    fixes = {}
    for name, var in ds.data_vars.items():
        if var.chunks is None:
            continue
        for dim, c in zip(var.dims, var.chunks):
            if len(c) > 1 and (len(set(c[:-1])) > 1 or c[-1] > c[0]):
                fixes[dim] = max(c)
    return ds.chunk(fixes) if fixes else ds


def write_zarr(
    obj: xr.DataArray | xr.Dataset,
    path: str | os.PathLike,
    *,
    mode: str = "w",
    compute: Callable | None = None,
) -> Path:
    """Write a DataArray or Dataset as a zarr v3 store, atomically.

    CRS and transform written by rioxarray (the ``spatial_ref`` coordinate)
    and all attrs (RPC dicts, provenance) are stored; dask-backed data is
    computed chunk by chunk straight into the store (zarr chunks = dask
    chunks).

    Parameters
    ----------
    obj : DataArray or Dataset
    path : path-like
        Store directory (conventionally ``*.zarr``).
    mode : {"w", "w-"}
        ``"w"`` replaces an existing store (atomically), ``"w-"`` refuses.
    compute : callable, optional
        ``compute(delayed)`` runs the write (e.g. with a progress bar or a
        distributed client); it receives the ``dask.delayed`` object of
        ``to_zarr(..., compute=False)``. Default: ``delayed.compute()``.

    Returns
    -------
    pathlib.Path
        The final store path.
    """
    if mode not in ("w", "w-"):
        raise ValueError(f"write_zarr: mode must be 'w' or 'w-', got {mode!r}")
    ds = _uniform_chunks(_clean_for_zarr(_as_dataset(obj)))
    final = Path(path)
    with atomic_path(final, overwrite=(mode == "w")) as tmp:
        delayed = ds.to_zarr(tmp, mode="w-", zarr_format=3, consolidated=False, compute=False)
        (compute or dask.compute)(delayed)
    return final


def _progress_array(path: Path):
    """Completion markers of a resumable store (read-only), None if plain."""
    if not (Path(path) / _PROGRESS / "done" / "zarr.json").is_file():
        return None
    return open_store_array(path, f"{_PROGRESS}/done", mode="r")


def _read_progress(path: Path) -> np.ndarray | None:
    """Completion markers of a resumable store, or None for a plain store."""
    arr = _progress_array(path)
    return None if arr is None else np.asarray(arr[...]).astype(bool)


def open_product(
    path: str | os.PathLike, chunks: "str | Mapping | None" = "native", allow_incomplete: bool = False
) -> xr.DataArray | xr.Dataset:
    """Open a product written by tiledsm (zarr store or GeoTIFF/COG).

    Parameters
    ----------
    path : path-like
        A ``.zarr`` store from :func:`write_zarr` / :func:`create_store`,
        or a GeoTIFF (opened like :func:`open_scene` without camera).
    chunks : "native", "auto", dict or None
        Dask chunks: ``"native"`` (default) one dask chunk per zarr chunk;
        other values are passed to ``xarray.open_zarr``.
    allow_incomplete : bool
        Open a resumable store that still has pending blocks.

    Returns
    -------
    DataArray or Dataset
        A DataArray when the store was written from one (same name, attrs,
        CRS via the ``spatial_ref`` coordinate), else a Dataset.

    Raises
    ------
    InputFileError
        Missing path, not a zarr store, or an incomplete store.
    """
    p = Path(path)
    if not p.exists():
        partial = Path(str(p) + ".partial")
        extra = f" (an unfinished store exists at {partial})" if partial.exists() else ""
        raise InputFileError(f"{p}: no such product{extra}")
    if p.is_file():
        return open_scene(p, require_camera=False, chunks=chunks if isinstance(chunks, (int, dict)) else 1024)
    try:
        ds = xr.open_zarr(
            p, chunks={} if chunks == "native" else chunks, decode_coords="all", consolidated=False, zarr_format=3
        )
    except (FileNotFoundError, KeyError, ValueError, OSError) as exc:
        raise InputFileError(f"{p}: not a readable zarr v3 store ({exc})") from exc
    done = _read_progress(p)
    if done is not None and not done.all() and not allow_incomplete:
        raise InputFileError(f"{p}: incomplete store ({int((~done).sum())} of {done.size} blocks pending)")
    ds.attrs.pop(_STORE_ATTR, None)
    name = ds.attrs.pop(_DA_ATTR, None)
    if name is None:
        return ds
    da = ds[name]
    if name == _UNNAMED:
        da.name = None
    return da


def open_raster_product(path: str | os.PathLike) -> xr.DataArray:
    """The 2-D raster of a tiledsm ``.zarr`` store, lazily: the store's
    DataArray, or a Dataset's ``height`` variable (its only 2-D variable
    otherwise), e.g. ``dsm.zarr`` of a DSM run.

    Raises
    ------
    InputFileError
        Not a readable store (:func:`open_product`), or no 2-D variable.
    """
    obj = open_product(path)
    if isinstance(obj, xr.Dataset):
        names = [n for n, v in obj.data_vars.items() if v.ndim == 2]
        if not names:
            raise InputFileError(f"{path}: zarr store holds no 2-D raster (variables: {', '.join(map(str, obj.data_vars))})")
        obj = obj["height" if "height" in names else names[0]]
    if obj.ndim != 2:
        raise InputFileError(f"{path}: expected a 2-D raster, the store holds a {obj.ndim}-D array")
    return obj


# --------------------------------------------------------------------------- resumable stores
@dataclass(frozen=True)
class ChunkStore:
    """Handle on a resumable zarr store filled block by block.

    Small and picklable (paths and ints only): pass it to dask tasks, which
    call :meth:`write_block` for their own block. Blocks are the zarr chunks
    along ``(y, x)``; leading dims (e.g. ``band``) are whole in every block.

    Attributes
    ----------
    path : str
        Final store path; the store lives at ``path + ".partial"`` until
        :meth:`finalize`.
    variables : tuple of str
        Data variables, all of shape ``shape``.
    shape : tuple of int
        Full shape, last two dims ``(y, x)``.
    chunk : (int, int)
        Block edge along ``y`` and ``x``, cells.
    """

    path: str
    variables: tuple[str, ...]
    shape: tuple[int, ...]
    chunk: tuple[int, int]

    @property
    def partial_path(self) -> Path:
        return Path(self.path + ".partial")

    @property
    def live_path(self) -> Path:
        """Where the store is now: the partial path, or the final one once finalized."""
        return self.partial_path if self.partial_path.exists() else Path(self.path)

    @property
    def numblocks(self) -> tuple[int, int]:
        return (-(-self.shape[-2] // self.chunk[0]), -(-self.shape[-1] // self.chunk[1]))

    def block_window(self, i: int, j: int) -> tuple[int, int, int, int]:
        """Half-open ``(row0, row1, col0, col1)`` of block ``(i, j)``."""
        nby, nbx = self.numblocks
        if not (0 <= i < nby and 0 <= j < nbx):
            raise GridError(f"{self.path}: block ({i}, {j}) outside the {nby}x{nbx} block layout")
        cy, cx = self.chunk
        return (i * cy, min((i + 1) * cy, self.shape[-2]), j * cx, min((j + 1) * cx, self.shape[-1]))

    def done(self) -> np.ndarray:
        """Boolean ``numblocks`` array: which blocks are written."""
        d = _read_progress(self.live_path)
        if d is None:
            raise InputFileError(f"{self.path}: not a resumable store (no {_PROGRESS}/done)")
        return d

    def blocks_done(self, blocks: Sequence[tuple[int, int]]) -> bool:
        """Whether every block of ``blocks`` is written (reads only their markers)."""
        arr = _progress_array(self.live_path)
        if arr is None:
            raise InputFileError(f"{self.path}: not a resumable store (no {_PROGRESS}/done)")
        return all(bool(arr[i, j]) for i, j in blocks)

    def pending(self) -> list[tuple[int, int]]:
        """Blocks still to write, row-major."""
        return [tuple(int(v) for v in ij) for ij in np.argwhere(~self.done())]

    @property
    def is_complete(self) -> bool:
        return bool(self.done().all())

    def write_block(self, i: int, j: int, values) -> None:
        """Write block ``(i, j)`` of every variable, then mark it done.

        Parameters
        ----------
        i, j : int
            Block index.
        values : array or mapping name -> array
            Shape ``shape[:-2] + (row1-row0, col1-col0)``; an array when the
            store has one variable.
        """
        if not isinstance(values, Mapping):
            if len(self.variables) != 1:
                raise ValueError(f"{self.path}: store has variables {self.variables}; pass a dict")
            values = {self.variables[0]: values}
        r0, r1, c0, c1 = self.block_window(i, j)
        where = str(self.live_path)
        for name in self.variables:
            if name not in values:
                raise ValueError(f"{self.path}: block ({i}, {j}) lacks variable {name!r}")
            v = np.asarray(values[name])
            expect = tuple(self.shape[:-2]) + (r1 - r0, c1 - c0)
            if v.shape != expect:
                raise ValueError(f"{self.path}: block ({i}, {j}) of {name!r} has shape {v.shape}, expected {expect}")
            arr = open_store_array(where, name, mode="r+")
            arr[(Ellipsis, slice(r0, r1), slice(c0, c1))] = v.astype(arr.dtype, copy=False)
        open_store_array(where, f"{_PROGRESS}/done", mode="r+")[i, j] = 1

    def finalize(self) -> Path:
        """Rename the complete store onto its final path (atomic).

        Raises
        ------
        TiledsmError
            Blocks are still pending.
        """
        final = Path(self.path)
        if not self.partial_path.exists():
            if final.exists():
                return final
            raise InputFileError(f"{self.path}: store vanished (neither it nor {self.partial_path} exists)")
        n = int((~self.done()).sum())
        if n:
            raise TiledsmError(f"{self.path}: cannot finalize, {n} blocks still pending")
        commit_path(self.partial_path, final)
        return final

    def open(self, allow_incomplete: bool = True):
        """The store as xarray (see :func:`open_product`)."""
        return open_product(self.live_path, allow_incomplete=allow_incomplete)


def _layout(ds_attrs: Mapping) -> dict | None:
    raw = ds_attrs.get(_STORE_ATTR)
    return json.loads(raw) if isinstance(raw, str) else raw


def create_store(
    path: str | os.PathLike,
    template,
    variables: Mapping[str, str] | Sequence[str] = ("data",),
    *,
    fill_value: float = float("nan"),
    attrs: Mapping | None = None,
    variable_attrs: Mapping[str, Mapping] | None = None,
    overwrite: bool = False,
) -> ChunkStore:
    """Create (or reopen for resume) a resumable chunked zarr v3 store.

    Parameters
    ----------
    path : path-like
        Final store path (``*.zarr``); the store is built at
        ``path + ".partial"`` until :meth:`ChunkStore.finalize`.
    template : GroundGrid or DataArray
        The grid: a :class:`~tiledsm.geometry.grid.GroundGrid` (dims
        ``(y, x)``, chunks ``grid.chunk``, CRS written), or a dask-backed
        DataArray whose dims end with ``(y, x)`` (its coords, CRS and
        ``y``/``x`` chunking are used; leading dims are one chunk).
    variables : sequence of names or mapping name -> dtype
        Data variables (default one ``float32`` variable ``"data"``).
    fill_value : float
        Value of never-written cells of float variables (integer variables
        use 0).
    attrs : mapping, optional
        Dataset attributes (provenance, recipe...).
    variable_attrs : mapping name -> mapping, optional
        Attributes of each variable (units...).
    overwrite : bool
        Start afresh even when a finished or partial store exists.

    Returns
    -------
    ChunkStore
        When a finished store exists at ``path`` (and not ``overwrite``) it
        is returned as is (all blocks done). When a compatible partial store
        exists, it is reused: its finished blocks are kept (resume). An
        incompatible partial store (other shape, chunks, variables or dtypes)
        is discarded.
    """
    import dask.array as dsa
    import zarr

    from tiledsm.geometry.grid import GroundGrid

    final = Path(path)
    if isinstance(variables, Mapping):
        var_dtypes = {str(k): np.dtype(v).name for k, v in variables.items()}
    else:
        var_dtypes = {str(k): "float32" for k in variables}
    if not var_dtypes:
        raise ValueError(f"{final}: create_store needs at least one variable")
    if isinstance(template, GroundGrid):
        dims, shape = ("y", "x"), template.shape
        chunk = (template.chunk, template.chunk)
        coords = template.coords()
        crs, transform = template.crs, template.transform
    elif isinstance(template, xr.DataArray):
        dims, shape = template.dims, tuple(template.shape)
        if dims[-2:] != ("y", "x"):
            raise GridError(f"{final}: template dims must end with (y, x), got {dims}")
        if template.chunks is None:
            raise GridError(f"{final}: template DataArray must be dask-backed (its chunks are the store's blocks)")
        cy, cx = template.chunks[-2], template.chunks[-1]
        chunk = (int(cy[0]), int(cx[0]))
        if any(c != chunk[0] for c in cy[:-1]) or any(c != chunk[1] for c in cx[:-1]):
            raise GridError(f"{final}: template chunks must be regular along y and x, got {cy}, {cx}")
        coords = {k: v for k, v in template.coords.items() if k != "spatial_ref"}
        crs = template.rio.crs
        transform = template.rio.transform() if "x" in template.coords and "y" in template.coords else None
    else:
        raise TypeError(f"create_store: template must be a GroundGrid or DataArray, got {type(template).__name__}")
    layout = {
        "shape": list(map(int, shape)),
        "dims": list(dims),
        "chunk": list(chunk),
        "variables": var_dtypes,
    }
    store = ChunkStore(str(final), tuple(var_dtypes), tuple(int(s) for s in shape), (int(chunk[0]), int(chunk[1])))
    partial = store.partial_path

    fingerprint = (attrs or {}).get("fingerprint")

    def reusable(p: Path) -> bool:
        """Whether the store at ``p`` can be resumed: same layout; and, when
        this run has a fingerprint, the same fingerprint (else the run stops
        naming what changed)."""
        try:
            with xr.open_zarr(p, consolidated=False, zarr_format=3) as ds:
                stored_attrs = dict(ds.attrs)
        except Exception as exc:  # an unreadable store is not reusable
            if fingerprint is not None:
                raise TiledsmError(f"{final}: an unreadable store is in the way ({exc}); rerun with --overwrite") from exc
            return False
        if fingerprint is not None:
            from tiledsm.provenance import check_resume

            stored = stored_attrs.get("fingerprint")
            stored = json.loads(stored) if isinstance(stored, str) else stored
            check_resume(stored if stored is not None else {}, json.loads(fingerprint), str(final))
        return _layout(stored_attrs) == layout and _read_progress(p) is not None

    if overwrite:
        remove_path(partial)
        remove_path(final)
    elif final.exists():
        if reusable(final):
            return store
        raise TiledsmError(f"{final}: exists with another layout; rerun with --overwrite to replace it")
    if partial.exists():
        if reusable(partial):
            return store
        remove_path(partial)

    full_chunks = tuple(-1 for _ in dims[:-2]) + chunk
    data_vars = {
        name: (
            dims,
            dsa.full(shape, fill_value if np.dtype(dt).kind == "f" else 0, dtype=dt, chunks=full_chunks),
            dict((variable_attrs or {}).get(name, {})),
        )
        for name, dt in var_dtypes.items()
    }
    ds = xr.Dataset(data_vars, coords=coords, attrs={**(attrs or {}), _STORE_ATTR: json.dumps(layout)})
    if crs is not None:
        ds = ds.rio.write_crs(crs)
        ds = ds.rio.write_transform(transform) if transform is not None else ds
    for name, enc in store_encoding(var_dtypes).items():
        ds[name].encoding.update(enc)  # beside rioxarray's grid_mapping
    with atomic_path(partial) as tmp:
        ds.to_zarr(tmp, mode="w-", zarr_format=3, consolidated=False, compute=False)
        prog = zarr.open_group(str(tmp), mode="a").require_group(_PROGRESS)
        prog.create_array("done", shape=store.numblocks, chunks=(1, 1), dtype="uint8", fill_value=0)
    return store


def _write_block_task(store: ChunkStore, i: int, j: int, names: tuple[str, ...], *blocks) -> bool:
    store.write_block(i, j, dict(zip(names, blocks)))
    return True


def write_blocks(data, store: ChunkStore, *, finalize: bool = True, compute: Callable | None = None) -> int:
    """Compute the pending blocks of ``data`` and write each one from its
    own dask task (the client only receives one boolean per block).

    Parameters
    ----------
    data : dask array, DataArray, or mapping name -> either
        Chunked exactly like the store along ``(y, x)``; leading dims one
        chunk. Blocks already marked done are culled from the graph, so
        their inputs are not computed either.
    store : ChunkStore
    finalize : bool
        Rename the store to its final path when every block is written.
    compute : callable, optional
        ``compute(delayed)`` runs the writes (progress bar, client...); it
        receives one ``dask.delayed`` object. Default: ``dask.compute``.

    Returns
    -------
    int
        Number of blocks written by this call.
    """
    import dask.array as dsa

    if not isinstance(data, Mapping):
        if len(store.variables) != 1:
            raise ValueError(f"{store.path}: store has variables {store.variables}; pass a dict")
        data = {store.variables[0]: data}
    names = tuple(store.variables)
    arrays = []
    for name in names:
        if name not in data:
            raise ValueError(f"{store.path}: no data given for variable {name!r}")
        a = data[name]
        a = a.data if isinstance(a, xr.DataArray) else a
        if not isinstance(a, dsa.Array):
            a = dsa.from_array(np.asarray(a), chunks=(-1,) * (np.ndim(a) - 2) + store.chunk)
        if tuple(a.shape) != store.shape:
            raise GridError(f"{store.path}: {name!r} has shape {a.shape}, store expects {store.shape}")
        if a.ndim > 2:
            a = a.rechunk((-1,) * (a.ndim - 2) + a.chunks[-2:])
        expect = tuple(
            tuple(min(c, n - k * c) for k in range(-(-n // c))) for n, c in zip(store.shape[-2:], store.chunk)
        )
        if tuple(a.chunks[-2:]) != expect:
            raise GridError(
                f"{store.path}: {name!r} chunks {a.chunks[-2:]} differ from the store's blocks {store.chunk}; "
                "rechunk the data (a block must map to exactly one zarr chunk)"
            )
        arrays.append(a)
    # no per-array graph optimisation: work the variables share (one kernel
    # producing height and confidence) keeps one key and runs once per block
    arrays = [a.to_delayed(optimize_graph=False).reshape(a.numblocks[-2:]) for a in arrays]
    pending = store.pending()
    tasks = [
        dask.delayed(_write_block_task, pure=False)(store, i, j, names, *(d[i, j] for d in arrays))
        for i, j in pending
    ]
    if tasks:
        (compute or dask.compute)(dask.delayed(len, pure=False)(tasks))
    if finalize:
        store.finalize()
    return len(tasks)


def write_resumable(
    obj: xr.DataArray | xr.Dataset,
    path: str | os.PathLike,
    *,
    compute: Callable | None = None,
    overwrite: bool = False,
    report: dict | None = None,
) -> Path:
    """Resumable counterpart of :func:`write_zarr`.

    Creates (or reopens) the store with :func:`create_store` from ``obj``'s
    grid, variables, dtypes and attrs, writes the pending blocks with
    :func:`write_blocks` and finalizes it. Re-running after a crash
    recomputes only the blocks that were not written; a finished store is
    left as is (pass ``overwrite=True`` to recompute). :func:`open_product`
    reads the result back like a :func:`write_zarr` store (a DataArray in,
    a DataArray out).

    Parameters
    ----------
    obj : DataArray or Dataset
        Dask-backed; all variables share dims ending with ``(y, x)`` and one
        regular chunking along them (the store's blocks).
    path : path-like
    compute : callable, optional
        See :func:`write_blocks`.
    overwrite : bool
        Discard existing (finished or partial) stores.
    report : dict, optional
        Filled with ``chunks_total``, ``chunks_reused``, ``chunks_computed``.

    Notes
    -----
    When ``obj.attrs`` holds a ``fingerprint`` (JSON of everything that
    determines the result, :mod:`tiledsm.provenance`), it is stored with the
    store at creation, and an existing finished or partial store is resumed
    only if its fingerprint is the same: otherwise
    :class:`~tiledsm.errors.FingerprintMismatchError` names what changed.
    """
    ds = _as_dataset(obj)
    variables = list(ds.data_vars)
    if not variables:
        raise ValueError(f"{path}: nothing to write (no data variables)")
    first = ds[variables[0]]
    for name in variables[1:]:
        if ds[name].dims != first.dims or ds[name].shape != first.shape:
            raise GridError(
                f"{path}: variable {name!r} has dims {ds[name].dims} / shape {ds[name].shape}, "
                f"expected those of {variables[0]!r}: {first.dims} / {first.shape}"
            )
    if first.chunks is None:
        first = first.chunk({"y": 1024, "x": 1024})
    store = create_store(
        path,
        first,
        {n: ds[n].dtype for n in variables},
        attrs=ds.attrs,
        variable_attrs={n: ds[n].attrs for n in variables},
        overwrite=overwrite,
    )
    chunks = dict(zip(first.dims[-2:], first.chunks[-2:]))
    total = int(np.prod(store.numblocks))
    written = write_blocks({n: ds[n].chunk(chunks) for n in variables}, store, compute=compute)
    if report is not None:
        report.update(chunks_total=total, chunks_reused=total - written, chunks_computed=written)
    log.info("%s: %d of %d chunks computed, %d reused from an earlier run", path, written, total, total - written)
    return Path(path)
