"""The process gives back what a phase frees (:mod:`tiledsm.allocator`)."""

import subprocess
import sys

import pytest

from tiledsm.allocator import ENV_VARS

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator: Linux only")

# A phase that frees 40 blocks of 8 MiB, each followed by a small block that stays (so the heap
# cannot be trimmed from its top), after a 16 MiB block raised glibc's mmap threshold: prints the
# MiB still resident once the 8 MiB blocks are freed.
PHASE = """
import numpy as np
def rss():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
big = np.ones(16 << 20, np.uint8); del big
r0 = rss()
blocks, kept = [], []
for _ in range(40):
    blocks.append(np.ones(8 << 20, np.uint8))
    kept.append(np.ones(64 << 10, np.uint8))
del blocks
print(round(rss() - r0))
"""

SETUPS = {
    "glibc's defaults": "",
    "return_freed_memory()": "from tiledsm.allocator import return_freed_memory; assert return_freed_memory()\n",
    # what the user types: every command goes through main()
    "the tiledsm command": "from tiledsm.cli import main\ntry:\n    main(['--version'])\nexcept SystemExit:\n    pass\n",
}


def _retained_mib(setup: str, env_extra: dict | None = None) -> int:
    import os

    env = {k: v for k, v in os.environ.items() if k not in ENV_VARS}
    env.update(env_extra or {})
    r = subprocess.run([sys.executable, "-c", setup + PHASE], capture_output=True, text=True, env=env, check=True)
    return int(r.stdout.split()[-1])


def test_freed_blocks_stay_resident_with_glibc_defaults():
    # the case this module exists for: 320 MiB freed, about 320 MiB still resident (measured 322)
    assert _retained_mib(SETUPS["glibc's defaults"]) > 250


@pytest.mark.parametrize("setup", ["return_freed_memory()", "the tiledsm command"])
def test_freed_blocks_go_back_to_the_system(setup):
    # measured: 2 MiB left of the 320 MiB freed
    assert _retained_mib(SETUPS[setup]) < 20


def test_a_users_own_setting_is_kept():
    # a user who asked glibc for a 64 MiB mmap threshold keeps it: the 8 MiB blocks stay resident
    assert _retained_mib(SETUPS["the tiledsm command"], {"MALLOC_MMAP_THRESHOLD_": str(64 << 20)}) > 250


# The matching's phase: the same 40 blocks freed inside heap_kept(16 MiB) stay in the heaps for the
# next task, and go back when the phase ends. Prints the MiB resident inside and after.
MATCHING = """
import numpy as np
from tiledsm.allocator import heap_kept, return_freed_memory
def rss():
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
fixed = return_freed_memory()
r0 = rss()
kept = []
with heap_kept(16 << 20) as active:
    blocks = []
    for _ in range(40):
        blocks.append(np.ones(8 << 20, np.uint8))
        kept.append(np.ones(64 << 10, np.uint8))
    del blocks
    inside = rss() - r0
print(fixed, active, round(inside), round(rss() - r0))
"""


def _matching_phase(env_extra: dict | None = None) -> list[str]:
    import os

    env = {k: v for k, v in os.environ.items() if k not in ENV_VARS}
    env.update(env_extra or {})
    return subprocess.run([sys.executable, "-c", MATCHING], capture_output=True, text=True, env=env,
                          check=True).stdout.split()


def test_the_matching_reuses_freed_blocks_and_gives_them_back_after():
    fixed, active, inside, after = _matching_phase()
    assert fixed == active == "True"
    # measured: 323 MiB resident inside (the next task's blocks come from there), 3 MiB after
    assert int(inside) > 250
    assert int(after) < 20


def test_the_matching_phase_leaves_a_users_setting_alone():
    # the user's own threshold (64 MiB) stays in force: heap_kept changes nothing, trims nothing
    fixed, active, inside, after = _matching_phase({"MALLOC_MMAP_THRESHOLD_": str(64 << 20)})
    assert fixed == active == "False"
    assert int(after) > 250
