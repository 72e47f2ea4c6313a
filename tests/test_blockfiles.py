"""tiledsm.io.BlockFiles: a grid's blocks as one file each, written and
read by many threads at once; a written block marks itself done, a store
of other attrs is emptied, a killed write leaves no block."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from tiledsm.errors import InputFileError
from tiledsm.io import BlockFiles


def _grid(shape=(250, 190), seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = rng.normal(300.0, 20.0, (2, *shape)).astype(np.float32)
    out[0, 10:40, 5:9] = np.nan  # holes survive
    return out


def _write_all(store: BlockFiles, values: np.ndarray, threads: int = 8) -> None:
    def one(ij):
        i, j = ij
        r0, r1, c0, c1 = store.block_window(i, j)
        store.write_block(i, j, {"height": values[0, r0:r1, c0:c1], "confidence": values[1, r0:r1, c0:c1]},
                          counts=(10 * i + j, 1))

    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(one, np.ndindex(*store.numblocks)))


def test_blocks_written_by_threads_read_back_in_any_window(tmp_path):
    values = _grid()
    store = BlockFiles(tmp_path / "L0.blocks", ("height", "confidence"), values.shape[1:], 64)
    store.prepare({"fingerprint": "a"})
    assert store.numblocks == (4, 3) and not store.done().any()
    _write_all(store, values)
    assert store.done().all()
    opened = BlockFiles.open(tmp_path / "L0.blocks")
    assert (opened.variables, opened.shape, opened.side) == (store.variables, store.shape, 64)
    np.testing.assert_array_equal(opened.read(0, 250, 0, 190, "height"), values[0])
    np.testing.assert_array_equal(opened.read(0, 250, 0, 190, "confidence"), values[1])
    # windows across block edges, and inside one block
    for r0, r1, c0, c1 in [(60, 70, 60, 130), (1, 249, 127, 190), (64, 128, 0, 64), (200, 201, 189, 190)]:
        np.testing.assert_array_equal(opened.read(r0, r1, c0, c1), values[0, r0:r1, c0:c1])
    # counts summed over the 12 blocks: 10 i + j, and 1 each
    assert opened.counts().tolist() == [sum(10 * i + j for i in range(4) for j in range(3)), 12]


def test_same_attrs_keep_the_blocks_other_attrs_empty_the_store(tmp_path):
    values = _grid()
    store = BlockFiles(tmp_path / "s", ("height", "confidence"), values.shape[1:], 100)
    store.prepare({"fingerprint": "a", "tasks": [3, 2]})
    _write_all(store, values)
    store.mark_computed(0, 0)
    assert store.computed() == 1
    # a resumed run: blocks kept, nothing computed yet by it
    store.prepare({"fingerprint": "a", "tasks": [3, 2]})
    assert store.done().all() and store.computed() == 0 and store.attrs()["fingerprint"] == "a"
    # another DSM: the store is emptied
    store.prepare({"fingerprint": "b", "tasks": [3, 2]})
    assert not store.done().any() and store.attrs()["fingerprint"] == "b"
    # another block side is another store, too
    BlockFiles(tmp_path / "s", ("height", "confidence"), values.shape[1:], 100).write_block(
        0, 0, {"height": values[0, :100, :100], "confidence": values[1, :100, :100]})
    BlockFiles(tmp_path / "s", ("height", "confidence"), values.shape[1:], 50).prepare({"fingerprint": "b",
                                                                                         "tasks": [3, 2]})
    assert not any((tmp_path / "s").glob("*.blk"))


def test_an_unfinished_write_is_no_block_and_is_cleared(tmp_path):
    store = BlockFiles(tmp_path / "s", ("height",), (64, 64), 64)
    store.prepare({"fingerprint": "a"})
    # what a run killed during a write leaves: the file beside, never renamed
    (tmp_path / "s" / "0_0.blk.tmp-1-2").write_bytes(b"\0" * 20)
    assert not store.blocks_done([(0, 0)])
    with pytest.raises(InputFileError, match=r"0_0\.blk: block \(0, 0\) is not written"):
        store.read(0, 64, 0, 64)
    store.prepare({"fingerprint": "a"})
    assert not list((tmp_path / "s").glob("*.tmp-*"))


def test_bad_blocks_are_refused_naming_the_store(tmp_path):
    store = BlockFiles(tmp_path / "s", ("height", "confidence"), (64, 64), 32)
    store.prepare({})
    with pytest.raises(ValueError, match="lacks variable 'confidence'"):
        store.write_block(0, 0, {"height": np.zeros((32, 32))})
    with pytest.raises(ValueError, match=r"has shape \(32, 31\), expected \(32, 32\)"):
        store.write_block(0, 0, {"height": np.zeros((32, 32)), "confidence": np.zeros((32, 31))})
    assert not store.done().any()
    with pytest.raises(InputFileError, match="not a block-files store"):
        BlockFiles.open(tmp_path / "elsewhere")
