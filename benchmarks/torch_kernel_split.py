"""Where the torch kernel's time goes on a device: cost volume against
aggregation, per task, and (on CUDA) the GPU operations launched.

The two tasks of ``benchmarks/profile_match.py`` (a ``SIZE``² scene, chunks
of 512), matched by the torch kernel on ``DEVICE`` with each step timed
(synchronised on CUDA) through a registered ``torch_timed`` kernel; the
last of 3 runs is kept. On CUDA one more run goes through
``torch.profiler``: the operations that used the GPU, their GPU time, and
the top of its table.

Usage::

    python3 benchmarks/torch_kernel_split.py cuda 1024 benchmarks/results/torch_kernel_split.json

Prints per task and writes the JSON (argument 3).
"""
import dataclasses, json, os, sys, time
from pathlib import Path
sys.path.insert(0, "benchmarks"); sys.path.insert(0, ".")
import numpy as np, torch
import profile_match
from tiledsm.cluster import single_threaded_libraries
import tiledsm.match.sgvll  # noqa: registers kernels
from tiledsm.match.kernels import MatchKernel, register_kernel
from tiledsm.match import torch_kernel as tk
from tiledsm.dsm import match_cells

dev = sys.argv[1] if len(sys.argv) > 1 else "cuda"
size = int(sys.argv[2]) if len(sys.argv) > 2 else 1024
out = Path(sys.argv[3]) if len(sys.argv) > 3 else Path("probe.json")
T = {}
def sync():
    if dev.startswith("cuda"): torch.cuda.synchronize()
def timed(name, f):
    def g(*a, **k):
        sync(); t = time.perf_counter(); r = f(*a, **k); sync()
        T.setdefault(name, []).append(time.perf_counter() - t); return r
    return g
register_kernel("torch_timed", MatchKernel(timed("cost_volume", tk.cost_volume), timed("aggregate", tk.aggregate), on_device=True))
single_threaded_libraries()
views, grid, h_range, levels, params = profile_match.setup(Path("runs/profile_match"), size, 512, 2)
coarse1 = profile_match.coarse_level(views, grid, h_range, levels, params)
todo = profile_match.tasks(views, grid, h_range, levels, params, coarse1)
res = {"device": dev, "name": torch.cuda.get_device_name() if dev.startswith("cuda") else "cpu", "torch": torch.__version__, "tasks": {}}
for name, (geom, cells, search) in todo.items():
    p = dataclasses.replace(params, match=dataclasses.replace(params.match, kernel="torch_timed", device=dev))
    for rep in range(3):
        T.clear(); sync(); t = time.perf_counter()
        match_cells(views, geom, cells, search, h_range, p); sync()
        wall = time.perf_counter() - t
    row = {"wall_s": wall, **{k: sum(v) for k, v in T.items()}}
    if dev.startswith("cuda"):
        from torch.profiler import profile, ProfilerActivity
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            match_cells(views, geom, cells, search, h_range, p); sync()
        ev = [e for e in prof.key_averages() if e.device_type.name == "CUDA" or getattr(e, "self_device_time_total", 0) > 0]
        row["cuda_kernels"] = int(sum(e.count for e in prof.key_averages() if getattr(e, "self_device_time_total", 0) > 0))
        row["gpu_busy_s"] = float(sum(getattr(e, "self_device_time_total", 0) for e in prof.key_averages())) / 1e6
        row["top"] = prof.key_averages().table(sort_by="self_cuda_time_total" if hasattr(prof.key_averages()[0], "self_cuda_time_total") else "self_device_time_total", row_limit=12)
    res["tasks"][name] = row
    print(name, {k: v for k, v in row.items() if k != "top"}, flush=True)
    if "top" in row: print(row["top"], flush=True)
out.write_text(json.dumps(res, indent=1))
