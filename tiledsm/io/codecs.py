"""How the resumable stores (:func:`tiledsm.io.create_store`) compress
their blocks.

Blosc's LZ4 after a byte shuffle. A matching run writes every block of
its pyramid levels and of the DSM, so the codec's time is on its
critical path. On 512² blocks of the 4096² synthetic scene's DSM
(``benchmarks/store_codec.py``, ``benchmarks/results/store_codec.json``)
it writes a block 3 to 4 times as fast as zarr's default (zstd level
0, no shuffle) and stores the heights in a smaller fraction of their raw
size (the shuffle groups the float32 values' exponent and high mantissa
bytes, which vary slowly over a surface). Blosc's zstd at level 1 stores
them about a tenth smaller again, at twice LZ4's writing time.
"""

from __future__ import annotations

import functools
from typing import Iterable

__all__ = ["BLOSC", "store_compressors", "block_codec", "store_encoding"]

#: Blosc's settings for every store of the project (zarr's names)
BLOSC = {"cname": "lz4", "clevel": 5, "shuffle": "shuffle"}


def store_compressors() -> tuple:
    """The zarr v3 compressors of a resumable store's variables."""
    from zarr.codecs import BloscCodec

    return (BloscCodec(**BLOSC),)


@functools.cache
def block_codec():
    """The same compression as a numcodecs codec, for the block files of
    :mod:`tiledsm.io.blockfiles` (numcodecs compresses without an event
    loop, in the calling thread)."""
    from numcodecs import Blosc

    return Blosc(cname=BLOSC["cname"], clevel=BLOSC["clevel"], shuffle=Blosc.SHUFFLE)


def store_encoding(variables: Iterable[str]) -> dict[str, dict]:
    """xarray ``to_zarr`` encoding giving each of ``variables`` the
    store's compressors."""
    return {name: {"compressors": store_compressors()} for name in variables}
