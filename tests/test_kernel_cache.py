"""Cached numba kernels follow the modules they import
(tiledsm.kernel_cache): a real kernel cached, its imported module edited,
the next start runs the new code."""

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import tiledsm
from tiledsm.kernel_cache import STATE_NAME, kernel_stamps, purge_stale_kernels

_KERNEL = """
import numba as nb
from kpkg.values import value

@nb.njit(cache=True)
def twice():
    return 2 * value()
"""

_VALUE = """
import numba as nb

@nb.njit(cache=True, inline="always")
def value():
    return {v}
"""


def _write(path: Path, text: str, tick: int) -> None:
    path.write_text(textwrap.dedent(text))
    # a distinct modification time, whatever the file system's resolution
    os.utime(path, ns=(tick * 10**9, tick * 10**9))


def _run(root: Path, purge: bool) -> int:
    code = "import sys\n"
    if purge:
        code += f"from tiledsm.kernel_cache import purge_stale_kernels\npurge_stale_kernels({str(root / 'kpkg')!r})\n"
    code += "from kpkg.kernel import twice\nprint(twice())\n"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["PYTHONPATH"] = os.pathsep.join([str(root), str(Path(tiledsm.__file__).parents[1])])
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return int(out.stdout.split()[-1])


def _package(root: Path) -> Path:
    """``kpkg``: a cached kernel inlining a function of another module."""
    pkg = root / "kpkg"
    pkg.mkdir()
    _write(pkg / "__init__.py", "", 1)
    _write(pkg / "kernel.py", _KERNEL, 1)
    _write(pkg / "values.py", _VALUE.format(v=1), 1)
    return pkg


def test_kernel_runs_new_code_after_its_imported_module_changes(tmp_path):
    pkg = _package(tmp_path)
    assert _run(tmp_path, purge=True) == 2
    assert list((pkg / "__pycache__").glob("kernel.twice-*.nbi")), "the kernel was not cached"

    _write(pkg / "values.py", _VALUE.format(v=5), 2)
    # the hazard: numba alone runs the cached kernel, compiled with value() = 1
    assert _run(tmp_path, purge=False) == 2
    assert _run(tmp_path, purge=True) == 10
    # and caches again: the next start loads it (its index not rewritten), nothing removed
    index = next((pkg / "__pycache__").glob("kernel.twice-*.nbi"))
    stamp = index.stat().st_mtime_ns
    assert _run(tmp_path, purge=True) == 10
    assert purge_stale_kernels(pkg) == []
    assert index.stat().st_mtime_ns == stamp


def test_only_dependent_kernels_are_removed(tmp_path):
    pkg = _package(tmp_path)
    _write(pkg / "other.py", "import numba as nb\n\n@nb.njit(cache=True)\ndef one():\n    return 1\n", 1)
    cache = pkg / "__pycache__"
    cache.mkdir()
    first = purge_stale_kernels(pkg)  # no state yet: every kernel module
    assert sorted(Path(p).name for p in first) == ["kernel.py", "other.py", "values.py"]
    for name in ("kernel.twice-5.py311.nbi", "values.value-4.py311.nbi", "other.one-3.py311.nbi", "kernel_x.f-1.py311.nbi"):
        (cache / name).write_text("")
    assert purge_stale_kernels(pkg) == []  # nothing changed: nothing read, nothing removed
    _write(pkg / "values.py", _VALUE.format(v=3), 2)
    assert sorted(Path(p).name for p in purge_stale_kernels(pkg)) == ["kernel.py", "values.py"]
    # other.py's kernel and a module whose name only begins like one are kept
    assert sorted(p.name for p in cache.glob("*.nbi")) == ["kernel_x.f-1.py311.nbi", "other.one-3.py311.nbi"]
    assert (cache / STATE_NAME).is_file()


def test_package_stamps_follow_the_sweep_imports(tmp_path):
    # a copy of tiledsm: bicubic sampling edited, every kernel inlining it restamped, no other
    copy = tmp_path / "tiledsm"
    shutil.copytree(Path(tiledsm.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    before = kernel_stamps(copy)
    with open(copy / "match" / "sampling.py", "a") as f:
        f.write("\n# edited\n")
    after = kernel_stamps(copy)
    changed = sorted(str(Path(p).relative_to(copy)) for p in before if before[p] != after[p])
    for name in ("match/_cuda_kernels.py", "match/sampling.py", "match/sweep.py", "match/sweep_reference.py"):
        assert name in changed, changed
    # kernels that import nothing of it keep their caches (modules whose
    # imports reach it through other packages, such as compare/stage.py, are
    # restamped: the imports are followed, not the names a kernel uses)
    for name in ("match/paths.py", "match/sgm.py", "match/winner.py", "match/zncc_rows.py", "match/cost.py",
                 "geometry/rpc.py", "synth/render.py", "io/overviews.py"):
        assert str(copy / name) in before and name not in changed, (name, changed)


def test_importing_tiledsm_keeps_the_state():
    # the package's own start runs the check (tiledsm/__init__.py)
    state = Path(tiledsm.__file__).parent / "__pycache__" / STATE_NAME
    subprocess.run([sys.executable, "-c", "import tiledsm"], check=True)
    assert state.is_file()
    assert purge_stale_kernels(Path(tiledsm.__file__).parent) == []
