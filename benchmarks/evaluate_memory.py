"""Peak memory of the displacement truth on a field grid: chunk by chunk
(``tiledsm evaluate``'s :func:`tiledsm.evaluate.displacement.truth_on_field`)
against the whole raster read at once (what the deformation runner did
until the scoring moved to :mod:`tiledsm.evaluate`).

    nice -n 10 .venv/bin/python benchmarks/evaluate_memory.py --sizes 2048 8192

For each size N, a truth raster of N x N float32 cells of 0.5 m (a smooth
field, tiled GeoTIFF, written block by block) is brought onto a field grid
of one cell every 8 pixels, once each way, each in its own process (its
peak RSS: ``getrusage``; the chunk-wise way runs dask's threads in that
process). Both results are compared cell by cell. Writes
``benchmarks/results/evaluate_memory.json``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

STEP = 8
X0, Y0, RES = 500000.0, 4000000.0, 0.5
CRS = "EPSG:32631"


def write_truth(path: Path, n: int) -> None:
    import rasterio
    from affine import Affine
    from rasterio.windows import Window

    prof = dict(driver="GTiff", width=n, height=n, count=1, dtype="float32", crs=CRS,
                transform=Affine(RES, 0, X0, 0, -RES, Y0), tiled=True, blockxsize=512, blockysize=512)
    with rasterio.open(path, "w", **prof) as dst:
        for r in range(0, n, 1024):
            rows = np.arange(r, min(n, r + 1024))[:, None]
            block = 1.5 * np.sin(rows / 97.0) * np.cos(np.arange(n)[None, :] / 131.0)
            dst.write(block.astype(np.float32), 1, window=Window(0, r, n, len(rows)))


def field_grid(n: int):
    from affine import Affine

    from tiledsm.evaluate.displacement import FieldGrid

    cells = n // STEP
    t = Affine(RES * STEP, 0, X0, 0, -RES * STEP, Y0)
    return FieldGrid(t, CRS, t.c + (np.arange(cells) + 0.5) * t.a, t.f + (np.arange(cells) + 0.5) * t.e, STEP)


def chunkwise(path: Path, n: int) -> np.ndarray:
    from tiledsm.evaluate.displacement import truth_on_field

    return truth_on_field(path, field_grid(n))


def whole(path: Path, n: int) -> np.ndarray:
    """The former way: the raster on the whole fine grid, then block means."""
    import rioxarray  # noqa: F401  (registers .rio)
    import xarray as xr
    from affine import Affine

    from tiledsm.workflows.common import reference_on_grid

    g = field_grid(n)
    t = Affine(g.transform.a / STEP, 0, g.transform.c, 0, g.transform.e / STEP, g.transform.f)
    ny, nx = g.shape[0] * STEP, g.shape[1] * STEP
    fine = xr.DataArray(np.zeros((ny, nx), np.float32), dims=("y", "x"),
                        coords={"y": t.f + (np.arange(ny) + 0.5) * t.e, "x": t.c + (np.arange(nx) + 0.5) * t.a})
    full = np.asarray(reference_on_grid(path, fine.rio.write_crs(CRS).rio.write_transform(t), "nearest").values,
                      np.float64)
    return full.reshape(g.shape[0], STEP, g.shape[1], STEP).mean(axis=(1, 3))


def child(way: str, path: Path, n: int, out: Path) -> None:
    t0 = time.perf_counter()
    field = {"chunkwise": chunkwise, "whole": whole}[way](path, n)
    wall = time.perf_counter() - t0
    np.save(out, field)
    print(json.dumps({"wall_s": wall, "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[2048, 8192])
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "evaluate_memory.json"))
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        way, path, n, out = args.child
        child(way, Path(path), int(n), Path(out))
        return 0
    rows = []
    load_before = os.getloadavg()
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            raster = Path(tmp) / f"truth_{n}.tif"
            write_truth(raster, n)
            fields = {}
            for way in ("whole", "chunkwise"):
                out = Path(tmp) / f"{way}_{n}.npy"
                done = subprocess.run([sys.executable, __file__, "--child", way, str(raster), str(n), str(out)],
                                      env=env, capture_output=True, text=True, check=True)
                m = json.loads(done.stdout.strip().splitlines()[-1])
                fields[way] = np.load(out)
                rows.append({"size": n, "field_cells": n // STEP, "way": way, **m})
                print(f"{n}² -> {n // STEP}² field, {way:9s}: {m['wall_s']:6.2f} s, "
                      f"peak RSS {m['peak_rss_mib']:6.0f} MiB")
            same = bool(np.array_equal(fields["whole"], fields["chunkwise"], equal_nan=True))
            for r in rows[-2:]:
                r["identical"] = same
            print(f"   identical: {same}")
    doc = {"script": "benchmarks/evaluate_memory.py", "date": _dt.datetime.now(_dt.timezone.utc).isoformat(),
           "command": " ".join(["benchmarks/evaluate_memory.py", "--sizes", *map(str, args.sizes)]),
           "step_px": STEP, "cpu_count": os.cpu_count(), "load_before": load_before, "load_after": os.getloadavg(),
           "rows": rows}
    Path(args.json).write_text(json.dumps(doc, indent=2))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
