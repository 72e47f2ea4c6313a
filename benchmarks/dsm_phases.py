"""Where the wall time of one ``tiledsm dsm`` command goes: its phases.

    nice -n 5 .venv/bin/python benchmarks/dsm_phases.py --cases synth4096

Runs the command (the cases of ``benchmarks/dsm.py``, threads, 2
workers) in a child process that wraps the DSM stage's functions with
timers before it calls the CLI (``tiledsm.cli.main``, in process: the
command's own code path), and reports:

- the serial phases, wall seconds from the process start: start-up
  (interpreter and imports until the command plans), planning (tie points
  and height range: ``prepare_views``; grid, graph), the matching graph
  (the level stores, the DSM store), the finish of the store, the exports
  (COG and quick-look, side by side) and the rest (metrics, exit);
- the matching graph's tasks: per pyramid level the tasks, their summed
  wall and **thread CPU** seconds (``time.thread_time``: on a shared
  machine other people's work stretches wall time far more than a
  thread's CPU time), the speckle filter's tasks, and the share of the
  graph's wall during which 2, 1 or 0 of its tasks run (both cores
  busy or not);
- the process's CPU seconds (``getrusage`` of the child: its native
  threads too, GDAL's and blosc's), CPU / wall, and the CPU seconds of its
  threads by name at the end (the workers, zarr's I/O loop, native
  threads; threads that ended together);
- with ``--stacks HZ``, where the matching tasks' threads are: every
  thread's Python stack sampled ``HZ`` times a second in the child
  (``sys._current_frames``: no ptrace, so it runs in containers that
  refuse py-spy), the functions holding the largest shares of the samples
  taken inside a task, and the collapsed stacks (flamegraph input) beside
  the events. A sample shows where a thread is, not whether it holds the
  GIL or waits for it.

``--device cuda --workers 16`` runs the GPU matching (on a GPU machine).

Writes ``benchmarks/results/dsm_phases.json``.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

REPO = Path(__file__).resolve().parent.parent

#: (module, function, phase tag): the functions the child times; the
#: graph's tasks (``match``, ``despeckle``) run on the workers' threads
TIMED = (
    ("tiledsm.dsm.stages", "_staged_task", "match"),
    ("tiledsm.dsm.stages", "_despeckled_task", "despeckle"),
    ("tiledsm.dsm", "prepare_views", "tie points and height range"),
    ("tiledsm.dsm.plan", "plan_dsm", "plan"),
    ("tiledsm.io", "write_resumable", "graph"),
    ("tiledsm.workflows.common", "write_dsm_products", "products"),
    ("tiledsm.io", "write_cog", "COG"),
    ("tiledsm.quicklook", "quicklook", "quick-look"),
    ("tiledsm.workflows.dsm", "run_dsm", "run"),
)


class StackSampler(threading.Thread):
    """Every other thread's Python stack, ``hz`` times a second, counted as
    collapsed stacks (``"outer (file:line);...;inner (file:line)"``)."""

    def __init__(self, hz: float):
        super().__init__(name="stack-sampler", daemon=True)
        self.period = 1.0 / hz
        self.counts: dict[str, int] = {}
        self.halt = threading.Event()

    def run(self) -> None:
        me = threading.get_ident()
        while not self.halt.wait(self.period):
            for tid, frame in sys._current_frames().items():
                if tid == me:
                    continue
                names = []
                while frame is not None:
                    code = frame.f_code
                    names.append(f"{code.co_name} ({Path(code.co_filename).name}:{frame.f_lineno})")
                    frame = frame.f_back
                key = ";".join(reversed(names))
                self.counts[key] = self.counts.get(key, 0) + 1


def top_functions(counts: dict[str, int], inside: str = "_staged_task", n: int = 25) -> list[dict]:
    """The functions (name and file) present in the largest shares of the
    stack samples taken inside ``inside`` (``function, samples, share``),
    then the innermost lines of the largest shares (``line`` rows: where
    the threads are)."""
    per: dict[str, int] = {}
    leaves: dict[str, int] = {}
    total = 0
    for stack, c in counts.items():
        lines = stack.split(";")
        frames = [f.rsplit(":", 1)[0] + ")" for f in lines]
        if not any(f.startswith(inside + " ") for f in frames):
            continue
        total += c
        leaves[lines[-1]] = leaves.get(lines[-1], 0) + c
        for f in set(frames[next(i for i, f in enumerate(frames) if f.startswith(inside + " ")):]):
            per[f] = per.get(f, 0) + c
    top = sorted(per.items(), key=lambda kv: -kv[1])[:n]
    inner = sorted(leaves.items(), key=lambda kv: -kv[1])[:n]
    return ([{"function": f, "samples": c, "share": round(c / total, 3)} for f, c in top]
            + [{"line": f, "samples": c, "share": round(c / total, 3)} for f, c in inner])


#: (label, frame prefix) of the waits :func:`wait_shares` counts, the
#: first that a sample's stack holds (opening a zarr array also waits on
#: zarr's loop: it comes before the loop)
WAITS = (
    ("numba-cuda context lookup", "get_or_create_context ("),
    ("zarr: opening an array", "open_array (synchronous.py"),
    ("zarr: its I/O loop (reads, writes)", "sync (sync.py"),
    ("numba: the compiler lock", "acquire (compiler_lock.py"),
)


def wait_shares(counts: dict[str, int], inside: tuple[str, ...] = ("_staged_task", "_despeckled_task")) -> dict:
    """Shares of the stack samples taken inside the graph's tasks (stacks
    holding a frame of ``inside``) that stand in each :data:`WAITS` entry;
    ``"samples"``: how many were taken inside."""
    out = {label: 0 for label, _ in WAITS}
    total = 0
    for stack, c in counts.items():
        if not any(f"{name} (" in stack for name in inside):
            continue
        total += c
        for label, prefix in WAITS:
            if prefix in stack:
                out[label] += c
                break
    return {"samples": total, **{k: round(v / total, 3) if total else 0.0 for k, v in out.items()}}


def _child(events_json: str, argv: list[str], stacks_hz: float = 0.0) -> None:
    """Time :data:`TIMED` (wall from this process's start, thread CPU, the
    level of a matching task) while ``tiledsm.cli.main(argv)`` runs; dump
    the events, the CLI's start and end and the process's CPU (and, with
    ``stacks_hz``, the sampled stacks: :class:`StackSampler`)."""
    import importlib

    t0 = time.perf_counter()
    events: list[dict] = []
    sampler = StackSampler(stacks_hz) if stacks_hz > 0 else None

    def wrap(module, name: str, tag: str) -> None:
        f = getattr(module, name)

        @functools.wraps(f)
        def timed(*a, **k):
            start, cpu = time.perf_counter(), time.thread_time()
            try:
                return f(*a, **k)
            finally:
                level = k.get("level")
                events.append({"tag": tag, "thread": threading.get_ident(), "start": start - t0,
                               "end": time.perf_counter() - t0, "thread_cpu": time.thread_time() - cpu,
                               "level": getattr(getattr(level, "geom", None), "level", None)})

        setattr(module, name, timed)

    for mod, name, tag in TIMED:
        wrap(importlib.import_module(mod), name, tag)
    from tiledsm.cli import main

    cli_start = time.perf_counter() - t0
    if sampler is not None:
        sampler.start()
    try:
        code = main(argv)
    except SystemExit as exc:  # the CLI's exit status
        code = exc.code
    if sampler is not None:
        sampler.halt.set()
        sampler.join()
    ru = resource.getrusage(resource.RUSAGE_SELF)
    Path(events_json).write_text(json.dumps({
        "code": code, "cli_start": cli_start, "cli_end": time.perf_counter() - t0,
        "cpu_s": ru.ru_utime + ru.ru_stime, "threads_cpu_s": thread_cpu(), "events": events,
        "stacks": sampler.counts if sampler is not None else None,
    }))


def thread_cpu() -> dict[str, float]:
    """CPU seconds of this process's live threads by name (a pool's
    threads together; threads without a Python name are native: GDAL's,
    blosc's). Threads that ended are not listed: the process's CPU less
    these is theirs."""
    import re

    names = {t.native_id: t.name for t in threading.enumerate()}
    tick = os.sysconf("SC_CLK_TCK")
    out: dict[str, float] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            fields = Path(f"/proc/self/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # ended meanwhile
            continue
        name = re.sub(r"[_-]\d+$", "", names.get(int(tid), "native"))
        out[name] = round(out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / tick, 2)
    return out


def _span(events: list[dict], tag: str) -> tuple[float, float] | None:
    ev = [e for e in events if e["tag"] == tag]
    return (min(e["start"] for e in ev), max(e["end"] for e in ev)) if ev else None


def concurrency(tasks: list[dict]) -> dict[int, float]:
    """Seconds of ``[first start, last end]`` of ``tasks`` during which
    0, 1, 2, ... of them run."""
    points = sorted([(e["start"], 1) for e in tasks] + [(e["end"], -1) for e in tasks])
    out: dict[int, float] = {}
    running, last = 0, points[0][0]
    for t, step in points:
        out[running] = out.get(running, 0.0) + t - last
        running, last = running + step, t
    return out


def phase_rows(doc: dict, wall: float) -> tuple[list[dict], dict]:
    """The serial phases (``phase, start_s, end_s, wall_s, share``) and the
    graph's task summary of one child's events."""
    ev = doc["events"]
    plan, tie = _span(ev, "plan"), _span(ev, "tie points and height range")
    graph, products = _span(ev, "graph"), _span(ev, "products")
    exports = [s for s in (_span(ev, "COG"), _span(ev, "quick-look")) if s]
    export = (min(s[0] for s in exports), max(s[1] for s in exports)) if exports else (graph[1], graph[1])
    marks = [
        ("start-up: interpreter, imports, options", 0.0, plan[0]),
        ("plan: tie points and height range", tie[0], tie[1]) if tie else None,
        ("plan: the rest (grid, levels, graph)", plan[0], plan[1]),
        ("run until the graph starts", plan[1], graph[0]),
        ("matching graph (levels, DSM store)", graph[0], graph[1]),
        ("store finished, levels removed", graph[1], export[0]),
        ("exports: COG beside quick-look", export[0], export[1]),
        ("metrics, summary, exit", export[1], wall),
    ]
    rows = []
    for m in marks:
        if m is None:
            continue
        name, a, b = m
        # the tie points lie inside the plan: its row is the plan less them
        d = (b - a) - ((tie[1] - tie[0]) if (tie and name.startswith("plan: the rest")) else 0.0)
        rows.append({"phase": name, "start_s": round(a, 2), "end_s": round(b, 2), "wall_s": round(d, 2),
                     "share": round(d / wall, 3)})
    tasks = [e for e in ev if e["tag"] in ("match", "despeckle")]
    conc = concurrency(tasks)
    span = sum(conc.values())
    levels = {}
    for lv in sorted({e["level"] for e in ev if e["tag"] == "match"}, reverse=True):
        lt = [e for e in ev if e["tag"] == "match" and e["level"] == lv]
        levels[f"L{lv}"] = {"tasks": len(lt), "task_wall_s": round(sum(e["end"] - e["start"] for e in lt), 2),
                            "thread_cpu_s": round(sum(e["thread_cpu"] for e in lt), 2)}
    sp = [e for e in ev if e["tag"] == "despeckle"]
    graph_summary = {
        "levels": levels,
        "despeckle": {"tasks": len(sp), "thread_cpu_s": round(sum(e["thread_cpu"] for e in sp), 2)},
        "tasks_span_s": round(span, 2),
        "share_of_span_with_tasks_running": {str(k): round(v / span, 3) for k, v in sorted(conc.items())},
    }
    return rows, graph_summary


def table(case: str, rows: list[dict], graph: dict, wall: float, cpu: float) -> str:
    lines = [f"### {case}: wall {wall:.1f} s, process CPU {cpu:.1f} s (CPU / wall {cpu / wall:.2f})", "",
             "| phase | wall (s) | share of wall |", "|---|---|---|"]
    lines += [f"| {r['phase']} | {r['wall_s']:.2f} | {100 * r['share']:.0f} % |" for r in rows]
    lines += ["", "| graph tasks | tasks | summed task wall (s) | thread CPU (s) |", "|---|---|---|---|"]
    lines += [f"| match {k} | {v['tasks']} | {v['task_wall_s']:.1f} | {v['thread_cpu_s']:.1f} |"
              for k, v in graph["levels"].items()]
    lines += [f"| speckle filter | {graph['despeckle']['tasks']} | | {graph['despeckle']['thread_cpu_s']:.1f} |", ""]
    busy = graph["share_of_span_with_tasks_running"]
    lines.append(f"Tasks run over {graph['tasks_span_s']:.1f} s: " + ", ".join(
        f"{k} running {100 * v:.0f} %" for k, v in busy.items()))
    threads = graph.get("threads_cpu_s", {})
    if threads:
        lines += ["", "Process CPU by thread (s): " + ", ".join(f"{k} {v:.1f}" for k, v in
                                                              sorted(threads.items(), key=lambda kv: -kv[1]))]
    waits = graph.get("stack_waits")
    if waits:
        lines += ["", f"Of {waits['samples']} stack samples inside the tasks: " + ", ".join(
            f"{k} {100 * v:.1f} %" for k, v in waits.items() if k != "samples")]
    if graph.get("stacks_top"):
        lines += ["", "| inside the matching tasks: function | share of samples |", "|---|---|"]
        lines += [f"| {r.get('function') or 'line ' + r['line']} | {100 * r['share']:.1f} % |"
                  for r in graph["stacks_top"]]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    if argv is None and len(sys.argv) > 3 and sys.argv[1] == "--child":
        _child(sys.argv[3], sys.argv[4:], float(sys.argv[2]))
        return 0
    from benchmarks._measure import write_result
    from benchmarks.dsm import case_args

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["synth4096"], help="s2p and/or synth<N>")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--device", default="cpu", help="tiledsm dsm --device: cpu, cuda, cuda:N")
    ap.add_argument("--stacks", type=float, default=0.0, metavar="HZ",
                    help="sample every thread's Python stack HZ times a second (0: not)")
    ap.add_argument("--run-dir", default=str(REPO / "runs" / "bench_dsm"))
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "dsm_phases.json"))
    args = ap.parse_args(argv)
    run_dir = Path(args.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    out_rows, tables = [], []
    for case in args.cases:
        dsm_args, facts = case_args(case, run_dir)
        name = case if args.device == "cpu" else f"{case}_{args.device.replace(':', '')}"
        out = run_dir / f"phases_{name}"
        subprocess.run(["rm", "-rf", str(out)], check=True)  # a finished store would be resumed
        events = run_dir / f"phases_{name}.json"
        argv_child = [sys.executable, str(Path(__file__).resolve()), "--child", str(args.stacks), str(events), "dsm",
                      *dsm_args, "--out", str(out), "--workers", str(args.workers), "--scheduler", "threads",
                      "--device", args.device, "--no-progress"]
        load_before = os.getloadavg()
        t0 = time.perf_counter()
        # this tree first, the caller's path after it (a GPU machine's wheels)
        path = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
        done = subprocess.run(argv_child, env=dict(os.environ, PYTHONPATH=path), capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if done.returncode != 0:
            raise SystemExit(f"{' '.join(argv_child)} failed:\n{done.stderr[-3000:]}")
        doc = json.loads(events.read_text())
        rows, graph = phase_rows(doc, wall)
        threads = doc["threads_cpu_s"]
        graph["threads_cpu_s"] = {**threads, "ended threads": round(doc["cpu_s"] - sum(threads.values()), 2)}
        stacks = doc.get("stacks")
        if stacks:
            graph["stacks_top"] = top_functions(stacks)
            graph["stack_waits"] = wait_shares(stacks)
            (run_dir / f"phases_{name}.stacks").write_text(
                "".join(f"{k} {v}\n" for k, v in sorted(stacks.items())))
        tables.append(table(name, rows, graph, wall, doc["cpu_s"]))
        print(tables[-1], flush=True)
        out_rows.append({"case": case, **{k: v for k, v in facts.items() if k in ("data", "reference")},
                         "device": args.device, "workers": args.workers, "scheduler": "threads",
                         "wall_s": round(wall, 2),
                         "cpu_s": round(doc["cpu_s"], 2), "mcells_per_s": None,
                         "load_before": list(load_before), "load_after": list(os.getloadavg()),
                         "phases": rows, "graph": graph})
        metrics = json.loads((out / "metrics.json").read_text())
        grid = metrics["report"]["grid"]
        out_rows[-1]["mcells_per_s"] = round(grid["width"] * grid["height"] / 1e6 / wall, 3)
    write_result(Path(args.json), "dsm_phases", "benchmarks/dsm_phases.py " + " ".join(argv or sys.argv[1:]),
                 out_rows, table="\n\n".join(tables))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
