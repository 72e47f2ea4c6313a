"""COG export time: GDAL's tile compression on one thread vs all cores, overviews streamed vs GDAL's.

    nice -n 5 .venv/bin/python benchmarks/cog.py [--sizes 4096 8192] [--repeat 2]

A synthetic DSM (smooth relief plus 0.1 m noise and 5 % holes, float32) of
each size, held in a zarr store as a DSM run leaves it, is exported by
:func:`tiledsm.io.write_cog` (DEFLATE, floating-point predictor, 512 px
tiles, overviews) at the DEFLATE level ``dsm.tif`` is written at
(:data:`tiledsm.workflows.common.DSM_DEFLATE_LEVEL`) three ways, in
alternation, ``--repeat`` times each: ``threads=1`` and
``threads="ALL_CPUS"`` (overviews averaged while the grid streams, the
default), and ``threads="ALL_CPUS"`` with ``overviews="gdal"`` (GDAL's
``COG`` driver reads the grid again to average them); a fourth way is all
cores at GDAL's default level (6), for the level's time and bytes. The
table gives the best wall time of each, checks that the two thread counts
wrote byte-identical files and that both overview routes wrote the same
values at every level. Writes
``benchmarks/results/cog.json``.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))


def synthetic_dsm(n: int, chunk: int = 1024):
    """A lazy ``n x n`` DSM DataArray (EPSG:32631, 0.5 m cells)."""
    import dask.array as da
    import rioxarray  # noqa: F401
    import xarray as xr
    from scipy import ndimage

    from tiledsm.geometry.grid import GroundGrid

    g = GroundGrid("EPSG:32631", 500_000.0, 4_900_000.0, 0.5, n, n, chunk)

    def block(block_info=None):
        (r0, r1), (c0, c1) = block_info[None]["array-location"]
        rng = np.random.default_rng(r0 * n + c0)
        y, x = np.mgrid[r0:r1, c0:c1] * 0.5
        z = 2000 + 40 * np.sin(x / 97.0) * np.cos(y / 131.0) + ndimage.uniform_filter(rng.normal(size=(r1 - r0, c1 - c0)), 5)
        z += rng.normal(size=z.shape) * 0.1
        z[rng.random(z.shape) < 0.05] = np.nan
        return z.astype(np.float32)

    data = da.map_blocks(block, chunks=g.chunks, dtype=np.float32, meta=np.empty((0, 0), np.float32))
    arr = xr.DataArray(data, dims=("y", "x"), coords=g.coords(), name="height")
    return arr.rio.write_crs(g.crs).rio.write_transform(g.transform)


def levels_equal(a: Path, b: Path) -> bool:
    """Whether two COGs hold the same values (NaN where NaN) at full resolution and every overview level."""
    import rasterio

    with rasterio.open(a) as fa, rasterio.open(b) as fb:
        n = len(fa.overviews(1))
        if n != len(fb.overviews(1)):
            return False
    for k in [None, *range(n)]:
        opts = {} if k is None else {"overview_level": k}
        with rasterio.open(a, **opts) as fa, rasterio.open(b, **opts) as fb:
            if not np.array_equal(fa.read(1), fb.read(1), equal_nan=True):
                return False
    return True


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[4096, 8192])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "cog.json"))
    args = ap.parse_args(argv)

    import dask

    from tiledsm.io import open_product, write_cog, write_zarr
    from tiledsm.workflows.common import DSM_DEFLATE_LEVEL

    rows = []
    with tempfile.TemporaryDirectory(prefix="tiledsm_bench_cog_") as tmp:
        for n in args.sizes:
            with dask.config.set(scheduler="threads"):
                store = write_zarr(synthetic_dsm(n), Path(tmp) / f"dsm_{n}.zarr")
            stored = open_product(store)
            lvl = DSM_DEFLATE_LEVEL
            ways = {"1": dict(threads=1, level=lvl), "ALL_CPUS": dict(threads="ALL_CPUS", level=lvl),
                    "gdal_overviews": dict(threads="ALL_CPUS", overviews="gdal", level=lvl),
                    "default_level": dict(threads="ALL_CPUS")}
            times: dict[str, list[float]] = {way: [] for way in ways}
            for _ in range(args.repeat):
                for way, kw in ways.items():
                    t = time.perf_counter()
                    write_cog(stored, Path(tmp) / f"dsm_{n}_{way}.tif", **kw)
                    times[way].append(time.perf_counter() - t)
            same = (Path(tmp) / f"dsm_{n}_1.tif").read_bytes() == (Path(tmp) / f"dsm_{n}_ALL_CPUS.tif").read_bytes()
            same_values = levels_equal(Path(tmp) / f"dsm_{n}_ALL_CPUS.tif", Path(tmp) / f"dsm_{n}_gdal_overviews.tif")
            row = {"size": n, "one_thread_s": min(times["1"]), "all_cpus_s": min(times["ALL_CPUS"]),
                   "gdal_overviews_s": min(times["gdal_overviews"]), "times_s": times, "identical_bytes": same,
                   "same_overview_values": same_values, "deflate_level": lvl,
                   "default_level_s": min(times["default_level"]),
                   "mib": round((Path(tmp) / f"dsm_{n}_1.tif").stat().st_size / 2**20, 1),
                   "default_level_mib": round((Path(tmp) / f"dsm_{n}_default_level.tif").stat().st_size / 2**20, 1)}
            row["speed_up"] = row["one_thread_s"] / row["all_cpus_s"]
            rows.append(row)
            print(f"{n}²: 1 thread {row['one_thread_s']:.2f} s, all cores {row['all_cpus_s']:.2f} s "
                  f"(x{row['speed_up']:.2f}), identical bytes: {same}; GDAL's overviews {row['gdal_overviews_s']:.2f} s, "
                  f"same values: {same_values}", file=sys.stderr)
    table = ["| grid | COG (MiB) | 1 thread (s) | all cores (s) | speed-up | identical bytes | all cores, GDAL's "
             "overviews (s) | same values | all cores, GDAL's default level (s) | its COG (MiB) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    table += [f"| {r['size']}² | {r['mib']} | {r['one_thread_s']:.2f} | {r['all_cpus_s']:.2f} | {r['speed_up']:.2f} | "
              f"{'yes' if r['identical_bytes'] else 'NO'} | {r['gdal_overviews_s']:.2f} | "
              f"{'yes' if r['same_overview_values'] else 'NO'} | {r['default_level_s']:.2f} | "
              f"{r['default_level_mib']} |" for r in rows]
    print("\n".join(table))
    doc = {"benchmark": "cog", "when": _dt.datetime.now().isoformat(timespec="seconds"),
           "command": " ".join([Path(sys.executable).name, *sys.argv]), "cpus": os.cpu_count(),
           "load_1min": os.getloadavg()[0], "rows": rows, "table": "\n".join(table)}
    Path(args.json).write_text(json.dumps(doc, indent=1))
    print(f"wrote {args.json}", file=sys.stderr)
    return 0 if all(r["identical_bytes"] and r["same_overview_values"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
