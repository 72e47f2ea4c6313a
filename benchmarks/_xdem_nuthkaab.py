"""xdem's Nuth & Kääb fit + apply on two DSM files, run by ``benchmarks/compare.py`` in xdem's own venv.

Usage (the venv holding xdem, never tiledsm's)::

    /work/peers/xdem/venv/bin/python benchmarks/_xdem_nuthkaab.py REF OTHER OUT.tif

Loads both DSMs (xdem holds them in memory), fits ``xdem.coreg.NuthKaab()``
(default parameters) of OTHER on REF, applies it to OTHER, writes the
aligned DSM to OUT.tif, and prints one JSON line: xdem's version, the shift
it found (``shift_x, shift_y`` in CRS units, ``shift_z`` in metres, xdem's
sign convention: the translation applied to OTHER) and seconds per step.
Only the standard library, numpy and xdem are imported (no tiledsm).
"""

import json
import sys
import time


def main() -> int:
    ref_path, other_path, out_path = sys.argv[1:4]
    t0 = time.perf_counter()
    import xdem

    t_import = time.perf_counter() - t0
    t1 = time.perf_counter()
    ref = xdem.DEM(ref_path)
    other = xdem.DEM(other_path)
    ref.load()
    other.load()
    t_load = time.perf_counter() - t1
    t2 = time.perf_counter()
    nk = xdem.coreg.NuthKaab()
    nk.fit(ref, other)
    t_fit = time.perf_counter() - t2
    t3 = time.perf_counter()
    aligned = nk.apply(other)
    t_apply = time.perf_counter() - t3
    t4 = time.perf_counter()
    aligned.save(out_path)
    t_save = time.perf_counter() - t4
    out = nk.meta["outputs"]["affine"]
    print(json.dumps({
        "xdem": xdem.__version__,
        "shift_x": float(out["shift_x"]), "shift_y": float(out["shift_y"]), "shift_z": float(out["shift_z"]),
        "timings_s": {"import": t_import, "load": t_load, "fit": t_fit, "apply": t_apply, "save": t_save},
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
