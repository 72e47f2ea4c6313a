"""A grid's blocks as one compressed file each, written and read by the
calling thread (:class:`BlockFiles`): the scratch stores of the DSM's
pyramid levels.

A matching task writes its block and reads its neighbours' while many
tasks run at once. Through zarr, every read and write of a process goes
through one I/O thread (zarr's event loop), so the writes of sixteen
threads queue behind each other (``benchmarks/store_writes.py``). Here a
block is compressed (Blosc LZ4 after a byte shuffle, the resumable stores'
codec: :mod:`tiledsm.io.codecs`) and written by the thread that made it,
and each thread decompresses what it reads; both release the GIL.

Layout of a folder::

    meta.json        shape, block side, variables, attrs (a fingerprint)
    <i>_<j>.blk      block (i, j): a header of int64 (two counts, then the
                     compressed size of each variable), then each
                     variable's float32 (rows, cols), compressed apart
                     (a reader of one variable reads and decompresses
                     only its bytes)
    computed/<i>_<j> empty: task (i, j) was computed by this run

A block file appears complete or not at all (written beside, then
renamed), so its presence marks the block done: a run killed in between
leaves the blocks it finished, and the next run with the same attrs
reuses them (:meth:`BlockFiles.prepare`).
"""

from __future__ import annotations

import json
import os
import shutil
import threading
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from tiledsm.errors import InputFileError
from tiledsm.io.codecs import block_codec

__all__ = ["BlockFiles"]

_FORMAT = "tiledsm-block-files-1"
_COUNTS = 2  # int64 counts at the head of a block file
_COMPUTED = "computed"


def _meta(folder: Path) -> dict | None:
    try:
        meta = json.loads((folder / "meta.json").read_text())
    except (OSError, ValueError):
        return None
    return meta if isinstance(meta, dict) and meta.get("format") == _FORMAT else None


class BlockFiles:
    """Float32 ``(rows, cols)`` variables of a grid, stored as one file per
    ``side x side`` block.

    Parameters
    ----------
    path : path-like
        The folder.
    variables : sequence of str
        Variable names, in the order of the values in a block file.
    shape : (int, int)
        Grid cells ``(rows, cols)``.
    side : int
        Block side, cells (the last row and column of blocks may be smaller).
    """

    def __init__(self, path: str | os.PathLike, variables: Sequence[str], shape: tuple[int, int], side: int) -> None:
        self.path = Path(path)
        self.variables = tuple(variables)
        self.shape = (int(shape[0]), int(shape[1]))
        self.side = int(side)

    @classmethod
    def open(cls, path: str | os.PathLike) -> BlockFiles:
        """The store in folder ``path``, as :meth:`prepare` described it.

        Raises
        ------
        InputFileError
            The folder holds no readable store of this format.
        """
        meta = _meta(Path(path))
        if meta is None:
            raise InputFileError(f"{path}: not a block-files store (no readable meta.json of {_FORMAT})")
        return cls(path, meta["variables"], tuple(meta["shape"]), meta["side"])

    def __repr__(self) -> str:
        return f"BlockFiles({str(self.path)!r}, {self.variables}, {self.shape}, side={self.side})"

    # ------------------------------------------------------------ geometry
    @property
    def numblocks(self) -> tuple[int, int]:
        return (-(-self.shape[0] // self.side), -(-self.shape[1] // self.side))

    def block_window(self, i: int, j: int) -> tuple[int, int, int, int]:
        """Half-open ``(row0, row1, col0, col1)`` of block ``(i, j)``."""
        s = self.side
        return i * s, min((i + 1) * s, self.shape[0]), j * s, min((j + 1) * s, self.shape[1])

    def blocks_under(self, r0: int, r1: int, c0: int, c1: int) -> list[tuple[int, int]]:
        """The blocks holding cells ``[r0:r1, c0:c1]``, row-major."""
        s = self.side
        return [(bi, bj) for bi in range(r0 // s, -(-r1 // s)) for bj in range(c0 // s, -(-c1 // s))]

    def _file(self, i: int, j: int) -> Path:
        return self.path / f"{i}_{j}.blk"

    # --------------------------------------------------------------- setup
    def attrs(self) -> dict | None:
        """The attrs given to :meth:`prepare`; ``None`` where the folder holds
        no readable store of this format."""
        meta = _meta(self.path)
        return None if meta is None else meta.get("attrs")

    def prepare(self, attrs: Mapping) -> None:
        """Make the folder ready for a run: kept (its finished blocks reused)
        when it holds a store of the same variables, grid and ``attrs``,
        otherwise emptied and made anew; in both cases no task is marked
        computed yet."""
        meta = {"format": _FORMAT, "shape": list(self.shape), "side": self.side, "variables": list(self.variables),
                "attrs": json.loads(json.dumps(dict(attrs)))}
        try:
            kept = json.loads((self.path / "meta.json").read_text()) == meta
        except (OSError, ValueError):
            kept = False
        if not kept and self.path.exists():
            shutil.rmtree(self.path)
        self.path.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(self.path / _COMPUTED, ignore_errors=True)
        (self.path / _COMPUTED).mkdir()
        for stale in self.path.glob("*.tmp-*"):  # a killed run's unfinished block
            stale.unlink(missing_ok=True)
        if not kept:
            self._replace(self.path / "meta.json", json.dumps(meta).encode())

    # ------------------------------------------------------------- writing
    def _replace(self, path: Path, data: bytes | Sequence[bytes]) -> None:
        tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}-{threading.get_ident()}")
        with open(tmp, "wb") as f:
            for part in [data] if isinstance(data, bytes) else data:
                f.write(part)
        os.replace(tmp, path)

    def write_block(self, i: int, j: int, values: Mapping[str, np.ndarray], counts: tuple[int, int] = (0, 0)) -> None:
        """Write block ``(i, j)`` of every variable and two counts with it
        (the DSM levels: candidate heights and searched cells), in one file
        that marks the block done.

        Raises
        ------
        ValueError
            A variable is missing or has another shape than the block.
        """
        r0, r1, c0, c1 = self.block_window(i, j)
        payloads = []
        for name in self.variables:
            if name not in values:
                raise ValueError(f"{self.path}: block ({i}, {j}) lacks variable {name!r}")
            v = np.asarray(values[name])
            if v.shape != (r1 - r0, c1 - c0):
                raise ValueError(f"{self.path}: block ({i}, {j}) of {name!r} has shape {v.shape}, "
                                 f"expected {(r1 - r0, c1 - c0)}")
            payloads.append(bytes(block_codec().encode(np.ascontiguousarray(v, np.float32))))
        header = np.array([*counts, *(len(p) for p in payloads)], np.int64).tobytes()
        self._replace(self._file(i, j), [header, *payloads])

    def mark_computed(self, i: int, j: int) -> None:
        """Mark task ``(i, j)`` as computed by this run."""
        (self.path / _COMPUTED / f"{i}_{j}").touch()

    # ------------------------------------------------------------- reading
    def blocks_done(self, blocks: Sequence[tuple[int, int]]) -> bool:
        """Whether every block of ``blocks`` is written."""
        return all(self._file(i, j).exists() for i, j in blocks)

    def done(self) -> np.ndarray:
        """Boolean ``numblocks`` array: which blocks are written."""
        out = np.zeros(self.numblocks, bool)
        for i, j in np.ndindex(*out.shape):
            out[i, j] = self._file(i, j).exists()
        return out

    def _block(self, i: int, j: int, k: int) -> np.ndarray:
        """Variable ``k`` of block ``(i, j)``."""
        path = self._file(i, j)
        n = _COUNTS + len(self.variables)
        try:
            with open(path, "rb") as f:
                # the header, then only this variable's bytes (a shared
                # file system moves half of a two-variable block)
                sizes = np.frombuffer(f.read(8 * n), np.int64)[_COUNTS:]
                f.seek(8 * n + int(sizes[:k].sum()))
                raw = f.read(int(sizes[k]))
        except FileNotFoundError:
            raise InputFileError(f"{path}: block ({i}, {j}) is not written") from None
        r0, r1, c0, c1 = self.block_window(i, j)
        out = np.empty((r1 - r0, c1 - c0), np.float32)
        block_codec().decode(raw, out=out)
        return out

    def read(self, r0: int, r1: int, c0: int, c1: int, variable: str | None = None) -> np.ndarray:
        """Cells ``[r0:r1, c0:c1]`` (inside the grid) of ``variable`` (the
        first by default); every block under them must be written.

        Raises
        ------
        InputFileError
            A block under the window is not written.
        """
        k = self.variables.index(variable or self.variables[0])
        out = np.empty((r1 - r0, c1 - c0), np.float32)
        for bi, bj in self.blocks_under(r0, r1, c0, c1):
            w0, w1, v0, v1 = self.block_window(bi, bj)
            a0, a1, b0, b1 = max(w0, r0), min(w1, r1), max(v0, c0), min(v1, c1)
            out[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = self._block(bi, bj, k)[a0 - w0 : a1 - w0, b0 - v0 : b1 - v0]
        return out

    def counts(self) -> np.ndarray:
        """``(2,)`` int64: the two counts summed over the written blocks."""
        total = np.zeros(2, np.int64)
        for path in self.path.glob("*.blk"):
            with open(path, "rb") as f:
                total += np.frombuffer(f.read(8 * _COUNTS), np.int64)
        return total

    def computed(self) -> int:
        """Tasks marked computed by this run."""
        folder = self.path / _COMPUTED
        return sum(1 for _ in folder.iterdir()) if folder.is_dir() else 0
