"""Where a whole run's client process peaks, with glibc's allocator as it comes and as ``tiledsm`` sets it.

Each case is ``tiledsm run RECIPE --out DIR`` on the shipped deformation
recipe (``input.synth.size`` set, the ``displacement:`` section left out, as
:mod:`benchmarks.workflow_memory` runs it), in a child process that runs the
command line in-process (:func:`tiledsm.cli.main`) beside a sampler thread.
Every 0.2 s the sampler reads the process's resident memory; at each new
peak (20 MiB above the last) it records the time and the main thread's
innermost ``tiledsm`` frames, so the peak is attributed to a phase (the
synthetic scene, the tie points, a DSM, the COG export, the comparison's
figures).

Two allocator settings, one child each:

- ``fixed``: the command as users run it: :func:`tiledsm.allocator.return_freed_memory`
  fixes glibc's mmap and trim thresholds at 1 MiB before anything else;
- ``glibc``: the same command with that call replaced by a no-op, so glibc
  keeps its dynamic mmap threshold (raised to every freed mapped block's
  size) and transients freed by one phase stay resident under the next.

Only the client is sampled (the workers of ``cluster.workers`` are other
processes; :mod:`benchmarks.workflow_memory` measures the whole tree).

Usage::

    nice -n 10 .venv/bin/python benchmarks/client_trace.py --sizes 1024

``--allocators fixed --append`` reruns one setting and keeps the results
file's other rows (each kept row says when it was measured).
Writes ``benchmarks/results/client_trace.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from benchmarks._measure import write_result  # noqa: E402

ALLOCATORS = ("glibc", "fixed")
INTERVAL_S = 0.2
STEP_MIB = 20.0


def _rss_mib() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _trace_child(allocator: str, argv: list[str], trace_json: Path) -> int:
    """Run ``tiledsm ARGV`` in this process, sampling its memory; write the peaks to ``trace_json``."""
    main_thread = threading.get_ident()
    t0 = time.perf_counter()
    peaks: list[dict] = []
    done = threading.Event()

    def sample() -> None:
        last = 0.0
        while not done.is_set():
            rss = _rss_mib()
            if rss > last + STEP_MIB:
                last = rss
                frame = sys._current_frames().get(main_thread)
                stack = traceback.extract_stack(frame) if frame is not None else []
                ours = [f"{Path(s.filename).parent.name}/{Path(s.filename).name}:{s.name}"
                        for s in stack if f"{os.sep}tiledsm{os.sep}" in s.filename][-3:]
                peaks.append({"t_s": round(time.perf_counter() - t0, 1), "rss_mib": round(rss, 1), "where": ours})
            time.sleep(INTERVAL_S)

    import tiledsm.allocator
    if allocator == "glibc":
        tiledsm.allocator.return_freed_memory = lambda *a, **k: False  # the call cli.main makes first
    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    from tiledsm.cli import main

    rc = main(argv)
    done.set()
    sampler.join()
    trace_json.write_text(json.dumps({"rc": rc, "wall_s": round(time.perf_counter() - t0, 1), "peaks": peaks}))
    return rc


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1024])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--runs", type=Path, default=REPO / "runs" / "client_trace")
    p.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "client_trace.json")
    p.add_argument("--allocators", nargs="+", choices=ALLOCATORS, default=list(ALLOCATORS))
    p.add_argument("--append", action="store_true",
                   help="keep the results file's rows of the sizes and allocators not run now")
    p.add_argument("--child", nargs=2, metavar=("ALLOCATOR", "TRACE_JSON"), help=argparse.SUPPRESS)
    args, rest = p.parse_known_args(argv)
    if args.child:
        return _trace_child(args.child[0], rest, Path(args.child[1]))

    from benchmarks.workflow_memory import _recipe

    recipe_args = argparse.Namespace(workers=args.workers, with_displacement=False, sr_models=[])
    rows = []
    for size in args.sizes:
        folder = args.runs / f"deformation_{size}"
        for allocator in args.allocators:
            shutil.rmtree(folder / f"run_{allocator}", ignore_errors=True)
        recipe = _recipe("deformation", size, folder, recipe_args)
        for allocator in args.allocators:
            out, trace = folder / f"run_{allocator}", folder / f"trace_{allocator}.json"
            cmd = [sys.executable, __file__, "--child", allocator, str(trace),
                   "run", str(recipe), "--out", str(out), "--no-progress"]
            with open(folder / f"run_{allocator}.log", "w") as log:
                r = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONPATH": str(REPO)})
            if r.returncode != 0 or not trace.exists():
                raise SystemExit(f"{' '.join(cmd)} failed (rc {r.returncode}); see {folder / f'run_{allocator}.log'}")
            doc = json.loads(trace.read_text())
            top = max(doc["peaks"], key=lambda s: s["rss_mib"])
            rows.append({"pipeline": "deformation", "size": size, "allocator": allocator, "wall_s": doc["wall_s"],
                         "client_peak_mib": top["rss_mib"], "peak_at_s": top["t_s"], "peak_where": top["where"],
                         "peaks": doc["peaks"]})
            print(f"deformation {size:5d} px  {allocator:5s}  {doc['wall_s']:7.1f} s  client peak {top['rss_mib']:7.1f} MiB "
                  f"at {top['t_s']} s in {' > '.join(top['where'])}", flush=True)
    command = "nice -n 10 .venv/bin/python benchmarks/client_trace.py " + " ".join(argv if argv is not None else sys.argv[1:])
    if args.append and args.json.exists():
        earlier = json.loads(args.json.read_text())
        done = {(r["size"], r["allocator"]) for r in rows}
        kept = [{"when": earlier["when"], **r} for r in earlier["rows"] if (r["size"], r["allocator"]) not in done]
        if kept:
            rows = sorted(kept + rows, key=lambda r: (r["size"], ALLOCATORS.index(r["allocator"])))
            command = f"{earlier['command']}; then {command}"
    print("\n| size (px) | allocator | wall (s) | client peak (MiB) | where |")
    print("|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['size']} | {r['allocator']} | {r['wall_s']} | {r['client_peak_mib']} | {' > '.join(r['peak_where'])} |")
    write_result(args.json, "client_trace", command, rows, interval_s=INTERVAL_S, step_mib=STEP_MIB)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
