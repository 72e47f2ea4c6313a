"""Peak memory of whole ``deformation`` and ``sr_dsm`` runs at two scene sizes (flat?).

Each case is ``tiledsm run RECIPE --out DIR`` as a user types it, on the
shipped recipe (``recipes/deformation.yaml``, ``recipes/experiments/sr_dsm.yaml``) with
``input.synth.size`` set, measured by :mod:`benchmarks._measure`: wall
time and the peak RSS of the largest process of the whole process tree
(the client and every dask worker; ``peak_single_rss_mib``), with the
client's and the largest worker's apart. Before it, ``tiledsm run ...
--dry-run`` prints the plan; its ``memory`` lines (each DSM's estimate per
worker) and ``grid`` lines are kept in the JSON.

Left out of the measured runs, and said so in the JSON: the deformation
recipe's ``displacement:`` section (the ortho correlation, measured by
``benchmarks/displacement_memory.py``; ``--with-displacement`` keeps it)
and, for ``sr_dsm``, the SR networks not in ``--sr-models`` (VDSR and SRMD
take minutes per 2048² image on two cores).

Usage::

    nice -n 10 .venv/bin/python benchmarks/workflow_memory.py --deformation-sizes 1024 4096 --sr-sizes 1024 4096

``--append`` keeps the rows already in the JSON of the pipelines not run
now (one pipeline measured again by a later, separate run; a pipeline run
now keeps only its new sizes, so its ratio is that of this run). Writes
``benchmarks/results/workflow_memory.json`` and prints a table;
``ratio`` is the larger size's largest-process peak over the smaller's
(target: <= 1.25).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
from benchmarks._measure import measure, write_result  # noqa: E402

RECIPES = {"deformation": REPO / "recipes" / "deformation.yaml", "sr_dsm": REPO / "recipes" / "experiments" / "sr_dsm.yaml"}
TARGET_RATIO = 1.25


def _recipe(pipeline: str, size: int, folder: Path, args) -> Path:
    """The shipped recipe with ``input.synth.size`` (and the cases' other settings) set."""
    doc = yaml.safe_load(RECIPES[pipeline].read_text())
    doc["input"]["synth"]["size"] = size
    doc["cluster"] = {"workers": args.workers}
    if pipeline == "deformation" and not args.with_displacement:
        doc.pop("displacement", None)
    if pipeline == "sr_dsm":
        doc["sr"]["models"] = list(args.sr_models)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "recipe.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _plan_lines(recipe: Path, out: Path) -> dict:
    """``tiledsm run --dry-run``: its wall time and its grid and memory lines."""
    r = subprocess.run([sys.executable, "-m", "tiledsm", "run", str(recipe), "--out", str(out), "--dry-run"],
                       capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO)})
    if r.returncode != 0:
        raise SystemExit(f"dry run of {recipe} failed:\n{r.stderr[-3000:]}")
    lines = [line.strip() for line in r.stdout.splitlines()]
    return {"memory": [line for line in lines if " memory " in f" {line} "],
            "grid": [line for line in lines if " grid " in f" {line} "]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--deformation-sizes", type=int, nargs="*", default=[1024, 4096])
    p.add_argument("--sr-sizes", type=int, nargs="*", default=[1024, 4096])
    p.add_argument("--sr-models", nargs="+", default=["dsm_upscale", "bicubic", "srcnn"])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--with-displacement", action="store_true")
    p.add_argument("--runs", type=Path, default=REPO / "runs" / "workflow_memory")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per run")
    p.add_argument("--json", type=Path, default=REPO / "benchmarks" / "results" / "workflow_memory.json")
    p.add_argument("--append", action="store_true",
                   help="keep the rows of --json for the pipelines not run now (e.g. one pipeline measured later)")
    args = p.parse_args(argv)

    rows = []
    cases = [("deformation", s) for s in args.deformation_sizes] + [("sr_dsm", s) for s in args.sr_sizes]
    for pipeline, size in cases:
        folder = args.runs / f"{pipeline}_{size}"
        shutil.rmtree(folder, ignore_errors=True)
        recipe = _recipe(pipeline, size, folder, args)
        out = folder / "run"
        plan = _plan_lines(recipe, out)
        m = measure([sys.executable, "-m", "tiledsm", "run", str(recipe), "--out", str(out), "--no-progress"],
                    env={**os.environ, "PYTHONPATH": str(REPO)}, log=folder / "run.out", interval=0.2,
                    timeout=args.timeout)
        row = {"pipeline": pipeline, "size": size, "ok": m.ok, "wall_s": round(m.wall_s, 1),
               "largest_process_mib": round(m.peak_single_rss_mib, 1),
               "client_mib": round(m.peak_root_rss_mib, 1), "largest_worker_mib": round(m.peak_descendant_rss_mib, 1),
               "plan": plan, "measurement": m.to_dict()}
        rows.append(row)
        print(f"{pipeline:12s} {size:6d} px  ok {m.ok}  {m.wall_s:7.1f} s  largest process "
              f"{m.peak_single_rss_mib:7.1f} MiB (client {m.peak_root_rss_mib:.0f}, worker "
              f"{m.peak_descendant_rss_mib:.0f})  load {m.load_before:.1f} -> {m.load_after:.1f}", flush=True)
        if not m.ok:
            print((folder / "run.out").read_text()[-3000:])
    earlier, before = [], ""
    if args.append and args.json.exists():
        ran = {r["pipeline"] for r in rows}
        doc = json.loads(args.json.read_text())
        earlier = [r for r in doc["rows"] if r["pipeline"] not in ran]
        before = doc["command"] + "; then "
    rows = earlier + rows
    ratios = {}
    for pipeline in ("deformation", "sr_dsm"):
        done = sorted((r for r in rows if r["pipeline"] == pipeline and r["ok"]), key=lambda r: r["size"])
        if len(done) >= 2:
            ratios[pipeline] = {"sizes": [done[0]["size"], done[-1]["size"]],
                                "ratio": round(done[-1]["largest_process_mib"] / done[0]["largest_process_mib"], 3),
                                "target": TARGET_RATIO}
    print("\n| pipeline | size (px) | wall (s) | largest process (MiB) | client (MiB) | largest worker (MiB) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['pipeline']} | {r['size']} | {r['wall_s']} | {r['largest_process_mib']} | {r['client_mib']} "
              f"| {r['largest_worker_mib']} |")
    for pipeline, ratio in ratios.items():
        print(f"{pipeline}: largest process {ratio['sizes'][1]} px / {ratio['sizes'][0]} px = {ratio['ratio']} "
              f"(target <= {TARGET_RATIO})")
    command = before + "nice -n 10 .venv/bin/python benchmarks/workflow_memory.py " + " ".join(argv or sys.argv[1:])
    write_result(args.json, "workflow_memory", command, rows, ratios=ratios,
                 left_out={"deformation": "displacement section" if not args.with_displacement else "nothing",
                           "sr_dsm": f"SR models other than {list(args.sr_models)}"})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
