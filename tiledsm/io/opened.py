"""Zarr arrays opened once per process (:func:`open_store_array`)."""

from __future__ import annotations

import os
import threading
from collections import OrderedDict

__all__ = ["open_store_array"]

#: arrays opened by :func:`open_store_array`: ``(store, path, mode) ->
#: (stamp of its zarr.json, array)``, the most recently used last
_OPENED: OrderedDict = OrderedDict()
_OPENED_LOCK = threading.Lock()
_OPENED_MAX = 256


def open_store_array(store: str | os.PathLike, path: str, mode: str = "r"):
    """``zarr.open_array(store=store, path=path, mode=mode)``, opened once per
    process while the array's ``zarr.json`` stays the same file.

    Opening reads and parses the metadata through zarr's I/O loop, one
    thread for the whole process: with sixteen threads opening the arrays
    of the DSM's level stores (then zarr) afresh for each task, 9 % of the
    tasks' stack samples stood there
    (``benchmarks/results/dsm_phases_gpu.json``), and a block's writes
    took 1.5-1.75x as long as with the arrays opened once
    (``benchmarks/store_writes.py``). An array is opened again when its
    metadata file was replaced (another inode, size or modification time:
    a store removed and made anew) and is not cached where it has none
    (zarr then raises its own error).
    """
    import zarr

    store = str(store)
    try:
        st = os.stat(os.path.join(store, path, "zarr.json"))
    except OSError:
        return zarr.open_array(store=store, path=path, mode=mode)
    key, stamp = (store, path, mode), (st.st_ino, st.st_size, st.st_mtime_ns)
    with _OPENED_LOCK:
        hit = _OPENED.get(key)
        if hit is not None and hit[0] == stamp:
            _OPENED.move_to_end(key)
            return hit[1]
    arr = zarr.open_array(store=store, path=path, mode=mode)
    with _OPENED_LOCK:
        _OPENED[key] = (stamp, arr)
        _OPENED.move_to_end(key)
        while len(_OPENED) > _OPENED_MAX:
            _OPENED.popitem(last=False)
    return arr
