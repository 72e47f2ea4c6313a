"""Time a ``tiledsm`` process spends after its command has returned.

    nice -n 5 .venv/bin/python benchmarks/exit_time.py [--repeat 5]

A child process imports what a DSM run imports (the DSM workflow, its
numba kernels compiled from their cache), runs ``tiledsm info`` on a file
(the ``s2p_pair``'s first image where ``../shared/data`` has it, else a
small synthetic GeoTIFF) through :func:`tiledsm.cli.main`, notes the
time, and ends either as Python does (``sys.exit``: the interpreter tears
down every module) or through :func:`tiledsm.cli.leave` (the exit
handlers, the flush, then ``os._exit``). The exit time is the child's
wall time, measured here, minus the time at which its command returned,
measured there. Both ways alternate ``--repeat`` times; the table gives
the median of each. Writes ``benchmarks/results/exit_time.json``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

CHILD = """
import sys, time
t0 = time.perf_counter()
import tiledsm.workflows.dsm  # what a DSM run imports
from tiledsm.match import sgm, sweep  # noqa: F401  (numba kernels)
from tiledsm.cli import leave, main
code = main(["info", sys.argv[2], "--json"])
print("RETURNED", time.perf_counter() - t0, file=sys.stderr, flush=True)
if sys.argv[1] == "leave":
    leave(code)
sys.exit(code)
"""


def _image(tmp: Path) -> Path:
    shared = Path(os.environ.get("TILEDSM_SHARED_DATA", REPO.parent / "shared" / "data"))
    img = shared / "s2p_pair" / "input_pair" / "img_01.tif"
    if img.exists():
        return img
    import numpy as np
    import rasterio

    path = tmp / "tiny.tif"
    with rasterio.open(path, "w", driver="GTiff", width=64, height=64, count=1, dtype="uint16") as ds:
        ds.write(np.arange(64 * 64, dtype=np.uint16).reshape(1, 64, 64))
    return path


def exit_time(how: str, image: Path) -> tuple[float, float]:
    """``(wall, after_return)`` of one child, seconds."""
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", CHILD, how, str(image)], capture_output=True, text=True, cwd=REPO)
    wall = time.perf_counter() - t
    if out.returncode != 0 or '"width"' not in out.stdout:
        raise RuntimeError(f"child ({how}) failed: rc {out.returncode}\n{out.stderr[-2000:]}")
    returned = float(next(ln for ln in out.stderr.splitlines() if ln.startswith("RETURNED")).split()[1])
    return wall, wall - returned


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "exit_time.json"))
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="tiledsm_bench_exit_") as tmp:
        image = _image(Path(tmp))
        exit_time("leave", image)  # numba's cache and the file cache warm
        runs: dict[str, list[tuple[float, float]]] = {"sys.exit": [], "leave": []}
        for _ in range(args.repeat):
            for how in runs:
                runs[how].append(exit_time(how, image))
    rows = [{"exit": how, "wall_s": statistics.median(w for w, _ in r), "after_return_s": statistics.median(a for _, a in r),
             "runs": r} for how, r in runs.items()]
    table = ["| how the process ends | whole process (s) | after the command returned (s) |", "|---|---|---|"]
    table += [f"| {r['exit']} | {r['wall_s']:.2f} | {r['after_return_s']:.2f} |" for r in rows]
    print("\n".join(table))
    doc = {"benchmark": "exit_time", "when": _dt.datetime.now().isoformat(timespec="seconds"),
           "command": " ".join([Path(sys.executable).name, *sys.argv]), "image": str(image), "cpus": os.cpu_count(),
           "load_1min": os.getloadavg()[0], "repeat": args.repeat, "rows": rows, "table": "\n".join(table)}
    Path(args.json).write_text(json.dumps(doc, indent=1))
    print(f"wrote {args.json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
