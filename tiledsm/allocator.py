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
its largest resident memory 1060 MiB with glibc's defaults, during the COG
export, and 649 MiB with a fixed 1 MiB mmap and trim threshold
(``MALLOC_MMAP_THRESHOLD_=1048576 MALLOC_TRIM_THRESHOLD_=1048576``), which
is what :func:`return_freed_memory` sets from inside the process.
"""

from __future__ import annotations

import ctypes
import os
import sys

__all__ = ["MMAP_THRESHOLD", "TRIM_THRESHOLD", "ENV_VARS", "return_freed_memory"]

#: blocks of at least this many bytes are mapped on their own and unmapped when freed
MMAP_THRESHOLD = 1 << 20
#: free memory at the top of a heap beyond this many bytes goes back to the system
TRIM_THRESHOLD = 1 << 20
#: glibc's environment variables for the same settings: a user who set one keeps their own
ENV_VARS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")

# mallopt parameters, <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


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
    if not sys.platform.startswith("linux") or any(name in os.environ for name in ENV_VARS):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # no glibc (musl has no mallopt)
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold)) and mallopt(_M_TRIM_THRESHOLD, int(trim_threshold)))
