"""The whole ``tiledsm dsm`` command, this tree against a git commit, in pairs.

    nice -n 5 .venv/bin/python benchmarks/dsm_paired.py --against REV [--cases synth4096] [--pairs 5]

On a shared machine the same command's wall time drifts by 10-20 % within
an hour, more than one change's gain. This script runs a case (the cases
of ``benchmarks/dsm.py``: ``s2p``, ``synth<N>``, 2 worker threads) with
the package of commit ``REV`` (``git archive`` into the run folder, first
on ``PYTHONPATH``) and with this tree's package, in turn: B A B A ...; each
pair's ratio A/B is taken on two runs minutes apart, so a drift of the
machine's speed moves both. The table gives each side's median wall time
and CPU seconds and its largest process's peak resident memory, the
median and range of the pair ratios, and checks
that both sides made the same DSM (NMAD and completeness against the
reference, scored apart from the timed command as ``benchmarks/dsm.py``
scores it). One uncounted run of each side comes first (``--warmup``:
an exported package compiles its kernels on its first run). Both sides run as ``python -m tiledsm`` from the run folder
(the console script of this tree would not start an older package).
Writes ``benchmarks/results/dsm_paired.json``: each row names its
baseline; ``--append`` keeps the file's rows of other cases or other
baselines (:func:`merge_rows`), so a change measured against its parent
does not erase rows that other pages read.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from benchmarks._measure import measure, scheduler_args, write_result  # noqa: E402
from benchmarks.blunders import export_rev  # noqa: E402
from benchmarks.dsm import case_args, score_run  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def run_once(dsm_args: list[str], reference: str, out: Path, src: Path, workers: int, timeout: float) -> dict:
    """One ``python -m tiledsm dsm`` with the package in ``src``; wall/CPU
    and the DSM's scores against ``reference`` (:func:`benchmarks.dsm.score_run`,
    this tree's scorer for both sides, untimed)."""
    shutil.rmtree(out, ignore_errors=True)  # a finished store would be resumed, not recomputed
    argv = [sys.executable, "-m", "tiledsm", "dsm", *dsm_args, "--out", str(out),
            *scheduler_args("threads", workers, out.parent), "--no-progress"]
    env = dict(os.environ, PYTHONPATH=str(src))
    m = measure(argv, cwd=out.parent, env=env, log=out.with_suffix(".log"), timeout=timeout)
    if not m.ok:
        raise SystemExit(f"{' '.join(argv)} failed (PYTHONPATH={src}); see {out.with_suffix('.log')}")
    ref, _ = score_run(out, reference, workers)
    return {"wall_s": m.wall_s, "cpu_s": m.cpu_s, "sys_s": m.sys_s_reaped, "largest_process_mib": m.peak_single_rss_mib,
            "nmad_m": ref.get("nmad"), "completeness": ref.get("completeness")}


def merge_rows(earlier: dict, rows: list[dict]) -> tuple[list[dict], str | None]:
    """The rows of an earlier results file ``earlier`` whose (case,
    baseline commit) was not run now, each with its ``when`` (and its
    baseline: files from before rows named theirs carry it at the top),
    followed by ``rows``; and the earlier command when a row was kept."""
    top = earlier.get("baseline")
    run_now = {(r["case"], r["baseline"]["commit"]) for r in rows}
    kept = []
    for r in earlier.get("rows", []):
        r = {"when": r.get("when", earlier.get("when")), **r}
        r.setdefault("baseline", top)
        if (r["case"], (r["baseline"] or {}).get("commit")) not in run_now:
            kept.append(r)
    return kept + rows, (earlier.get("command") if kept else None)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", required=True, help="git commit (or any rev) whose package is the baseline B")
    ap.add_argument("--cases", nargs="+", default=["synth4096"], help="s2p and/or synth<N>")
    ap.add_argument("--pairs", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=1, help="uncounted runs of each side first")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--run-dir", default=str(REPO / "runs" / "bench_dsm"))
    ap.add_argument("--timeout", type=float, default=3600)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "dsm_paired.json"))
    ap.add_argument("--append", action="store_true",
                    help="keep the results file's rows of the cases or baselines not run now")
    args = ap.parse_args(argv)
    run_dir = Path(args.run_dir).absolute()  # the commands run from its parent
    run_dir.mkdir(parents=True, exist_ok=True)
    base_src, commit = export_rev(args.against, run_dir)
    rows = []
    for case in args.cases:
        args_of_case, info = case_args(case, run_dir)
        # a freshly exported package compiles its kernels on its first run (numba's cache)
        for side, src in (("B", base_src), ("A", REPO)):
            for _ in range(args.warmup):
                run_once(args_of_case, info["reference_path"], run_dir / f"paired_{case}_{side}", src, args.workers, args.timeout)
        runs = {"A": [], "B": []}
        for k in range(args.pairs):
            for side, src in (("B", base_src), ("A", REPO)):
                r = run_once(args_of_case, info["reference_path"], run_dir / f"paired_{case}_{side}", src, args.workers, args.timeout)
                runs[side].append(r)
                print(f"{case} pair {k + 1} {side}: {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU", file=sys.stderr)
        ratios = [a["wall_s"] / b["wall_s"] for a, b in zip(runs["A"], runs["B"])]
        same = all(a["nmad_m"] == runs["B"][0]["nmad_m"] and a["completeness"] == runs["B"][0]["completeness"]
                   for a in runs["A"] + runs["B"])
        rows.append({
            "case": case, **info, "baseline": {"rev": args.against, "commit": commit}, "workers": args.workers,
            "pairs": args.pairs,
            "a_wall_s_median": statistics.median(r["wall_s"] for r in runs["A"]),
            "b_wall_s_median": statistics.median(r["wall_s"] for r in runs["B"]),
            "a_cpu_s_median": statistics.median(r["cpu_s"] for r in runs["A"]),
            "b_cpu_s_median": statistics.median(r["cpu_s"] for r in runs["B"]),
            "a_sys_s_median": statistics.median(r["sys_s"] for r in runs["A"]),
            "b_sys_s_median": statistics.median(r["sys_s"] for r in runs["B"]),
            "a_largest_process_mib_median": statistics.median(r["largest_process_mib"] for r in runs["A"]),
            "b_largest_process_mib_median": statistics.median(r["largest_process_mib"] for r in runs["B"]),
            "ratio_wall_median": statistics.median(ratios), "ratio_wall_min": min(ratios), "ratio_wall_max": max(ratios),
            "same_scores": same, "runs": runs,
        })
    command = " ".join([Path(sys.executable).name, *sys.argv])
    measured = list(rows)
    if args.append and Path(args.json).exists():
        rows, earlier_command = merge_rows(json.loads(Path(args.json).read_text()), rows)
        if earlier_command:
            command = f"{earlier_command}; then {command}"
    table = ["| case | baseline | pairs | this tree: wall (s), CPU (s) (system), largest process (MiB) | baseline: "
             "wall (s), CPU (s) (system), largest process (MiB) | wall ratio A/B, median (range) | same NMAD and "
             "completeness |", "|---|---|---|---|---|---|---|"]
    table += [f"| {r['case']} | {(r['baseline'] or {}).get('commit', '?')[:7]} | {r['pairs']} | "
              f"{r['a_wall_s_median']:.1f}, {r['a_cpu_s_median']:.1f} "
              f"({r['a_sys_s_median']:.1f}), {r['a_largest_process_mib_median']:.0f} | {r['b_wall_s_median']:.1f}, "
              f"{r['b_cpu_s_median']:.1f} ({r['b_sys_s_median']:.1f}), "
              f"{r['b_largest_process_mib_median']:.0f} | {r['ratio_wall_median']:.3f} "
              f"({r['ratio_wall_min']:.3f}-{r['ratio_wall_max']:.3f}) | {'yes' if r['same_scores'] else 'NO'} |" for r in rows]
    print("\n".join(table))
    write_result(Path(args.json), "dsm_paired", command, rows,
                 baseline={"rev": args.against, "commit": commit}, table="\n".join(table))
    return 0 if all(r["same_scores"] for r in measured) else 1


if __name__ == "__main__":
    raise SystemExit(main())
