"""SGVLL on the real Pleiades pair of s2p, on the grid of s2p's own DSM
(0.5 m, UTM 40S, 721x739 cells), compared with that DSM."""

import numpy as np
import pytest

from tiledsm.geometry import RPC
from tiledsm.match.sgvll import SGVLLParams, match_pyramid
from tiledsm.match.tiepoints import height_range_from_tiepoints, match_tiepoints, relative_correction


@pytest.mark.slow
@pytest.mark.realdata
def test_s2p_pair_against_s2p_dsm(shared_data):
    import rasterio

    rpcs, imgs = [], []
    for name in ("img_01.tif", "img_02.tif"):
        with rasterio.open(shared_data("s2p_pair", "input_pair", name)) as ds:
            rpcs.append(RPC.from_gdal(ds.rpcs.to_dict(), source=name))
            imgs.append(ds.read(1).astype(np.float32))
    with rasterio.open(shared_data("s2p_pair", "expected_output", "pair", "dsm.tif")) as ds:
        ref, T, crs = ds.read(1), ds.transform, ds.crs.to_string()
    gx = T.c + (np.arange(ref.shape[1]) + 0.5) * T.a
    gy = T.f + (np.arange(ref.shape[0]) + 0.5) * T.e
    r1, r2 = rpcs
    p1, p2 = match_tiepoints(*imgs)
    drow, dcol = relative_correction(r1, r2, p1, p2)
    r2 = r2.replace(line_off=r2.line_off + drow, samp_off=r2.samp_off + dcol)
    lo, hi = height_range_from_tiepoints(r1, r2, p1, p2, margin=10.0)
    h, conf = match_pyramid(imgs, [r1, r2], None, gx, gy, crs, lo, hi, SGVLLParams())
    e = (h - ref)[np.isfinite(h) & np.isfinite(ref)]
    nmad = 1.4826 * np.median(np.abs(e - np.median(e)))
    completeness = np.isfinite(h).mean()
    # measured: NMAD 0.32 m, median -0.02 m, completeness 94 % (issue bounds: 0.5 m, 90 %)
    assert nmad <= 0.5, nmad
    assert completeness >= 0.9, completeness
    assert abs(np.median(e)) < 0.2
