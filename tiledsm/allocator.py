"""Give the memory a phase frees back to the operating system (glibc's allocator).

A command's own process goes through phases that each allocate and free a
transient of tens to hundreds of MiB: the synthetic scene, SIFT's scale
space on the tie points' overviews, the COG export, the comparison's
figures. glibc serves a block above its *mmap threshold* with ``mmap`` and
unmaps it when freed, but it raises that threshold to the size of every
such block freed (up to 32 MiB on 64-bit systems): from then on blocks of
that size come from the heaps, which are trimmed only from their top, and
stay in the process after they are freed. Each phase's transient then adds
to the resident memory instead of replacing the previous one's.

Measured on the deformation recipe at ``input.synth.size: 1024`` (2 cores,
the client process sampled every 0.2 s, ``benchmarks/client_trace.py``):
its largest resident memory was 1060 MiB with glibc's defaults, during the
COG export, and is 623 MiB with a fixed 1 MiB mmap and trim threshold
(``MALLOC_MMAP_THRESHOLD_=1048576 MALLOC_TRIM_THRESHOLD_=1048576``), which
is what :func:`return_freed_memory` sets from inside the process
(``client_trace.json``).

The exceptions are the block passes: each matching task, and each block of
the comparison's fit and difference pass, allocates and frees its 1-64 MiB
temporaries again (cost volumes, image windows, zarr chunks, histogram
partials), and mapping them afresh makes the kernel zero every page of
every one. :func:`heap_kept` raises the thresholds while such a pass runs,
so freed blocks are reused from the heaps, then gives the heaps back
(``malloc_trim``) and restores the thresholds for the phases after it.
Measured on ``tiledsm dsm`` at 4096² (2 threads, ``benchmarks/allocator.py``;
the Memory page) and on ``tiledsm compare`` at 8192² (``benchmarks/compare.py``).
"""

from __future__ import annotations

import ctypes
import functools
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["MMAP_THRESHOLD", "TRIM_THRESHOLD", "MATCHING_MMAP_THRESHOLD", "ENV_VARS", "heap_kept",
           "return_freed_memory"]

#: blocks of at least this many bytes are mapped on their own and unmapped when freed
MMAP_THRESHOLD = 1 << 20
#: free memory at the top of a heap beyond this many bytes goes back to the system
TRIM_THRESHOLD = 1 << 20
#: while the matching runs (:func:`heap_kept`): blocks below this many bytes are reused from the heaps
MATCHING_MMAP_THRESHOLD = 16 << 20
#: glibc's environment variables for the same settings: a user who set one keeps their own
ENV_VARS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")

# mallopt parameters, <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

#: the thresholds :func:`return_freed_memory` set in this process (``None``: not set)
_fixed: tuple[int, int] | None = None


@functools.lru_cache(maxsize=None)
def _libc():
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
        libc.mallopt.restype = ctypes.c_int
        libc.malloc_trim.argtypes = (ctypes.c_size_t,)
        libc.malloc_trim.restype = ctypes.c_int
    except (OSError, AttributeError):  # no glibc (musl has no mallopt)
        return None
    return libc


def _set(libc, mmap_threshold: int, trim_threshold: int) -> bool:
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold))
                and libc.mallopt(_M_TRIM_THRESHOLD, int(trim_threshold)))


def return_freed_memory(mmap_threshold: int = MMAP_THRESHOLD, trim_threshold: int = TRIM_THRESHOLD) -> bool:
    """Fix glibc's mmap and trim thresholds of this process (module notes).

    Setting the mmap threshold also stops glibc from raising it, so blocks
    of ``mmap_threshold`` bytes or more are always unmapped when freed.

    Parameters
    ----------
    mmap_threshold, trim_threshold : int
        Bytes.

    Returns
    -------
    bool
        Whether the thresholds were set: ``False`` off glibc (another C
        library, another system) or where the user set one of
        :data:`ENV_VARS` (their choice is kept).
    """
    global _fixed
    if not sys.platform.startswith("linux") or any(name in os.environ for name in ENV_VARS):
        return False
    libc = _libc()
    if libc is None or not _set(libc, mmap_threshold, trim_threshold):
        return False
    _fixed = (int(mmap_threshold), int(trim_threshold))
    return True


@contextmanager
def heap_kept(mmap_threshold: int | None = None) -> Iterator[bool]:
    """Reuse freed blocks below ``mmap_threshold`` bytes (default
    :data:`MATCHING_MMAP_THRESHOLD`) from the heaps while the body runs.

    For a phase that allocates and frees blocks of the same sizes again
    and again (the matching's tasks): served from the heaps, they are not
    mapped and zeroed afresh each time. On exit every heap's free memory
    goes back to the system (``malloc_trim(0)``) and the thresholds of
    :func:`return_freed_memory` are restored.

    Does nothing (yields ``False``) where :func:`return_freed_memory` did
    not set them: another C library, the user's own ``MALLOC_*``
    settings, ``tiledsm`` imported as a library.
    """
    threshold = MATCHING_MMAP_THRESHOLD if mmap_threshold is None else int(mmap_threshold)
    libc = _libc() if _fixed is not None else None
    if libc is None or not _set(libc, threshold, 2 * threshold):
        yield False
        return
    try:
        yield True
    finally:
        _set(libc, *_fixed)
        libc.malloc_trim(0)
