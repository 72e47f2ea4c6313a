"""The matching's temporaries reused from the heaps or mapped afresh: ``tiledsm dsm`` at three thresholds.

    nice -n 5 .venv/bin/python benchmarks/allocator.py [--case synth4096] [--pairs 2]

Every command fixes glibc's mmap threshold at 1 MiB so that each phase
gives back what it frees (:mod:`tiledsm.allocator`); while the matching
runs, :func:`tiledsm.allocator.heap_kept` raises it to
``MATCHING_MMAP_THRESHOLD`` so that the tasks' temporaries are reused
instead of mapped and zeroed afresh. This script runs the whole
``tiledsm dsm`` command (a case of ``benchmarks/dsm.py``, 2 worker
threads) with that threshold at 1 MiB (nothing kept), at the default and
at 32 MiB (glibc's own ceiling), in turn, ``--pairs`` rounds, each in a
child process that sets the module's value and then runs the command line
in-process (:func:`tiledsm.cli.main`). It records each run's wall time,
CPU seconds and their system part (the kernel's page faults and mappings),
and its largest process, and checks that every run made the same DSM
(NMAD and completeness against the truth, scored apart from the timed
command). Writes ``benchmarks/results/allocator.json``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from benchmarks._measure import measure, scheduler_args, write_result  # noqa: E402
from benchmarks.dsm import case_args, score_run  # noqa: E402

MIB = 1 << 20
CHILD = "import sys, tiledsm.allocator as a; a.MATCHING_MMAP_THRESHOLD = int(sys.argv[1]); " \
        "from tiledsm.cli import main; sys.exit(main(sys.argv[2:]))"


def run_once(threshold: int, dsm_args: list[str], reference: str, out: Path, workers: int) -> dict:
    """One ``tiledsm dsm`` with the matching's mmap threshold at ``threshold`` bytes."""
    shutil.rmtree(out, ignore_errors=True)  # a finished store would be resumed, not recomputed
    argv = [sys.executable, "-c", CHILD, str(threshold), "dsm", *dsm_args, "--out", str(out),
            *scheduler_args("threads", workers, out.parent), "--no-progress"]
    # a MALLOC_* variable would switch the thresholds off (the user's setting wins)
    env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    env["PYTHONPATH"] = str(REPO)  # this tree's package, whatever the venv has installed
    m = measure(argv, cwd=out.parent, env=env, log=out.with_suffix(".log"))
    if not m.ok:
        raise SystemExit(f"tiledsm dsm failed with threshold {threshold}; see {out.with_suffix('.log')}")
    ref, _ = score_run(out, reference, workers)
    return {"wall_s": m.wall_s, "cpu_s": m.cpu_s, "sys_s": m.sys_s_reaped, "largest_process_mib": m.peak_single_rss_mib,
            "nmad_m": ref.get("nmad"), "completeness": ref.get("completeness"), "load_before": m.load_before}


def main(argv: list[str] | None = None) -> int:
    from tiledsm.allocator import MATCHING_MMAP_THRESHOLD, MMAP_THRESHOLD

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="synth4096", help="s2p or synth<N> (benchmarks/dsm.py)")
    ap.add_argument("--pairs", type=int, default=2, help="rounds of the three thresholds")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--run-dir", default=str(REPO / "runs" / "bench_dsm"))
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "allocator.json"))
    args = ap.parse_args(argv)
    run_dir = Path(args.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    dsm_args, info = case_args(args.case, run_dir)
    thresholds = sorted({MMAP_THRESHOLD, MATCHING_MMAP_THRESHOLD, 32 * MIB})
    runs: dict[int, list[dict]] = {t: [] for t in thresholds}
    for k in range(args.pairs):
        for t in thresholds:
            r = run_once(t, dsm_args, info["reference_path"], run_dir / f"allocator_{args.case}", args.workers)
            runs[t].append(r)
            print(f"round {k + 1}, {t // MIB} MiB: {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU "
                  f"({r['sys_s']:.1f} system), {r['largest_process_mib']:.0f} MiB", file=sys.stderr)
    first = runs[thresholds[0]][0]
    rows = [{
        "case": args.case, **info, "workers": args.workers, "rounds": args.pairs,
        "matching_mmap_threshold_mib": t // MIB, "default": t == MATCHING_MMAP_THRESHOLD,
        "wall_s_median": statistics.median(r["wall_s"] for r in runs[t]),
        "cpu_s_median": statistics.median(r["cpu_s"] for r in runs[t]),
        "sys_s_median": statistics.median(r["sys_s"] for r in runs[t]),
        "largest_process_mib_median": statistics.median(r["largest_process_mib"] for r in runs[t]),
        "same_dsm_scores": all(r["nmad_m"] == first["nmad_m"] and r["completeness"] == first["completeness"]
                               for r in runs[t]),
        "runs": runs[t],
    } for t in thresholds]
    table = ["| matching's mmap threshold | wall (s) | CPU (s) | of which system (s) | largest process (MiB) | "
             "same DSM |", "|---|---|---|---|---|---|"]
    table += [f"| {r['matching_mmap_threshold_mib']} MiB{' (default)' if r['default'] else ''} | "
              f"{r['wall_s_median']:.1f} | {r['cpu_s_median']:.1f} | {r['sys_s_median']:.1f} | "
              f"{r['largest_process_mib_median']:.0f} | {'yes' if r['same_dsm_scores'] else 'NO'} |" for r in rows]
    print("\n".join(table))
    write_result(Path(args.json), "allocator", " ".join([Path(sys.executable).name, *sys.argv]), rows,
                 table="\n".join(table))
    return 0 if all(r["same_dsm_scores"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
