"""Comparison statistics of tiledsm.workflows.sr_dsm: every compared DSM is
scored on the common cells (reference and every DSM valid), each with its own
completeness. Oracle: small grids with known holes and known errors."""

from __future__ import annotations

import numpy as np
import pytest

from tiledsm.evaluate.sr_dsm import score_tables as _score_tables
from tiledsm.workflows.sr_figures import blunder_map
from tiledsm.workflows.sr_scores import (
    BLUNDER_K,
    REGIONS,
    RegionRule,
    blunder_cells,
    common_valid,
    compare_by_region,
    regions_from_truth,
    compare_on_common,
    markdown_report,
    own_completeness,
    scores_on,
)

HOLE_A = (1, 1)  # A has no height here; B has a 100 m blunder
HOLE_B = (2, 2)  # B has no height here; A has a 50 m blunder
NO_REF = (0, 0)  # the reference has no height here


def _case(blunder_b: float = 100.0):
    """Reference (5 x 4 cells, one without height) and two DSMs whose
    errors are 0.1 m (A) and +-0.2 m (B) except where the other has a hole."""
    ref = 100.0 + np.arange(20, dtype=np.float64).reshape(5, 4)
    ref[NO_REF] = np.nan
    a = ref + 0.1
    a[HOLE_A] = np.nan
    a[HOLE_B] = ref[HOLE_B] + 50.0
    sign = np.where(np.indices(ref.shape).sum(0) % 2 == 0, 1.0, -1.0)
    b = ref + 0.2 * sign
    b[HOLE_B] = np.nan
    b[HOLE_A] = ref[HOLE_A] + blunder_b
    return ref, a, b


def test_common_valid_is_the_intersection():
    ref, a, b = _case()
    ok = common_valid(ref, a, b)
    expected = np.ones(ref.shape, bool)
    for cell in (NO_REF, HOLE_A, HOLE_B):
        expected[cell] = False
    np.testing.assert_array_equal(ok, expected)
    np.testing.assert_array_equal(common_valid(a), np.isfinite(a))
    with pytest.raises(ValueError, match="different shapes"):
        common_valid(a, b[:-1])
    with pytest.raises(ValueError, match="at least one"):
        common_valid()


def test_statistics_are_on_the_common_cells():
    ref, a, b = _case()
    res = compare_on_common({"A": a, "B": b}, ref)
    assert res["common"] == {"count": 17, "cells": 19, "fraction": pytest.approx(17 / 19), "dsms": ["A", "B"]}
    sa, sb = res["scores"]["A"], res["scores"]["B"]
    # A: 0.1 m everywhere on the common cells; its 50 m blunder sits where B has a hole
    assert sa["rmse"] == pytest.approx(0.1) and sa["max"] == pytest.approx(0.1) and sa["nmad"] == pytest.approx(0.0, abs=1e-12)
    # B: +-0.2 m; its 100 m blunder sits where A has a hole
    assert sb["rmse"] == pytest.approx(0.2) and sb["max"] == pytest.approx(0.2) and sb["min"] == pytest.approx(-0.2)
    common = common_valid(ref, a, b)
    assert sb["mre"] == pytest.approx(np.mean(0.2 / ref[common]))
    assert sa["count"] == sb["count"] == 17
    # each DSM's own completeness: 18 of the 19 reference cells
    for s in (sa, sb):
        assert (s["valid"], s["cells"]) == (18, 19) and s["completeness"] == pytest.approx(18 / 19)


def test_a_blunder_under_another_dsms_hole_changes_nothing():
    ref, a, b = _case(blunder_b=100.0)
    _, a2, b2 = _case(blunder_b=1e6)
    first, second = compare_on_common({"A": a, "B": b}, ref), compare_on_common({"A": a2, "B": b2}, ref)
    assert first == second
    # scored alone, each DSM's blunder counts: the intersection is what removed it
    alone = compare_on_common({"A": a}, ref)["scores"]["A"]
    assert alone["max"] == pytest.approx(50.0) and alone["rmse"] > 10


def test_mask_restricts_the_evaluated_cells():
    ref, a, b = _case()
    mask = np.ones(ref.shape, bool)
    mask[4] = False  # last row: 4 cells, all valid in ref, A and B
    res = compare_on_common({"A": a, "B": b}, ref, mask)
    assert (res["common"]["count"], res["common"]["cells"]) == (13, 15)
    assert res["scores"]["A"]["completeness"] == pytest.approx(14 / 15)


def test_scores_on_and_own_completeness():
    ref = np.array([[10.0, 20.0], [np.nan, 40.0]])
    h = np.array([[11.0, np.nan], [5.0, 38.0]])
    cells = np.array([[True, False], [False, True]])
    s = scores_on(h, ref, cells)
    assert (s["count"], s["cells"]) == (2, 2)
    assert s["mean"] == pytest.approx(-0.5) and s["rmse"] == pytest.approx(np.sqrt(2.5))
    assert own_completeness(h, np.isfinite(ref)) == {"valid": 2, "cells": 3, "completeness": pytest.approx(2 / 3)}
    assert np.isnan(own_completeness(h, np.zeros_like(cells))["completeness"])


def _metrics(hr, methods, refs):
    scores, common = _score_tables(hr, methods, refs)
    return {
        "name": "synthetic", "input": "test arrays",
        "sr": {"degrade": "bicubic", "scale": 2, "bit_depth": 12, "border": 2},
        "grid": {"resolution": 0.5, "width": hr.shape[1], "height": hr.shape[0]},
        "hr": {"dsm": {}, **scores.get("hr", {})},
        "methods": {name: scores[name] for name in methods},
        "common": common,
        "timings": {"hr": 1.0},
    }


def test_tables_score_on_their_common_cells_and_say_so():
    """Table 2 (vs the HR-pair DSM): the methods' common cells; Table 3 (vs
    the truth on visible cells): the HR pair's and the methods' common cells."""
    truth, a, b = _case()
    hr = truth + 0.05
    hr[3, 3] = np.nan  # the HR pair misses a cell: out of Table 3's common cells
    visible = np.ones(truth.shape, bool)
    visible[4, 0] = False
    metrics = _metrics(hr, {"bicubic": a, "srcnn": b}, {"vs_truth_visible": (truth, visible)})
    assert metrics["common"]["vs_hr"]["count"] == 16  # 20 - no truth - holes A, B - HR hole
    assert metrics["common"]["vs_truth_visible"]["count"] == 15  # and the invisible cell
    assert metrics["methods"]["bicubic"]["vs_hr"]["rmse"] == pytest.approx(0.05)
    assert metrics["methods"]["bicubic"]["vs_truth_visible"]["rmse"] == pytest.approx(0.1)
    assert metrics["hr"]["vs_truth_visible"]["completeness"] == pytest.approx(17 / 18)
    report = markdown_report(metrics)
    print(report)
    table2 = report.split("**Table 2.**")[1].split("**Table 3.**")[0]
    table3 = report.split("**Table 3.**")[1]
    assert "Scored on 16 common cells (88.9 % of the 18 cells of the HR-pair DSM)" in table2
    assert "Scored on 15 common cells (83.3 % of the 18 cells of the reference)" in table3
    assert "| Bicubic | 0.050 |" in table2 and "| HR pair | 0.050 |" in table3
    assert "| Bicubic | 0.100 |" in table3 and "94.4 |" in table3  # own completeness 17/18


def test_a_runs_own_report_has_table_1_and_says_where_the_dsm_tables_are():
    """A run's ``report.md`` (no DSM rows: ``tiledsm evaluate`` scores them)."""
    truth, a, _ = _case()
    metrics = _metrics(truth, {"bicubic": a}, {})
    metrics["methods"]["bicubic"] = {"image": {"psnr_db": 31.5, "ssim": 0.91}, "dsm": {}}
    metrics["hr"] = {"dsm": {}}
    del metrics["common"]
    report = markdown_report(metrics)
    assert "| Bicubic | 31.50 | 0.9100 |" in report
    assert "**Table 2.**" not in report and "**Table 3.**" not in report
    assert "`tiledsm evaluate` on this run folder writes them into `evaluation/report.md`" in report


def test_report_without_common_block_still_renders():
    """Metrics written before common-cell scoring (no ``common``) still render."""
    truth, a, b = _case()
    metrics = _metrics(truth, {"bicubic": a}, {})
    del metrics["common"]
    assert "Scored on" not in markdown_report(metrics)


def _blunder_case():
    """100 cells: 48 errors of +0.1 m, 48 of -0.1 m, 2 of +10 m, 2 of -10 m.
    Median 0, median |error| 0.1 m, so NMAD = 0.14826 m and the blunders
    (|error - median| > 3 NMAD = 0.445 m) are exactly the four 10 m cells."""
    err = np.array([0.1] * 48 + [-0.1] * 48 + [10.0] * 2 + [-10.0] * 2).reshape(10, 10)
    ref = 200.0 + np.arange(100.0).reshape(10, 10)
    return ref + err, ref, np.abs(err) > 1.0


def test_blunders_are_errors_beyond_three_nmad():
    h, ref, truth = _blunder_case()
    blunders, threshold = blunder_cells(h, ref, np.ones(h.shape, bool))
    assert threshold == pytest.approx(BLUNDER_K * 1.4826 * 0.1, rel=1e-9)
    np.testing.assert_array_equal(blunders, truth)
    s = scores_on(h, ref, np.ones(h.shape, bool))
    assert s["blunder_rate"] == pytest.approx(0.04) and s["blunder_threshold"] == pytest.approx(threshold)
    # only scored cells count: masking two blunders out leaves 2 of 98
    cells = np.ones(h.shape, bool)
    cells[9, 8:] = False
    assert scores_on(h, ref, cells)["blunder_rate"] == pytest.approx(2 / 98)
    h2 = h.copy()
    h2[9, 9] = np.nan  # a hole is not a blunder
    assert not blunder_cells(h2, ref, np.ones(h.shape, bool))[0][9, 9]
    empty, t = blunder_cells(h, ref, np.zeros(h.shape, bool))
    assert not empty.any() and np.isnan(t)
    # a bias is not a blunder: the threshold is around the median error
    np.testing.assert_array_equal(blunder_cells(h + 3.0, ref, np.ones(h.shape, bool))[0], truth)


def _regions_case():
    """40 x 40 cells of 1 m: the west half a plane rising 1 m per metre to
    the east (45 deg), the east half flat, one 6 x 6 building on the flat
    half, a 4 x 4 tree, and a 3-cell-wide band hidden from a view."""
    z = np.zeros((40, 40))
    z[:, :20] = np.arange(20.0)[None, :]
    z[:, 20:] = 19.0
    label = np.zeros((40, 40), np.uint8)
    label[5:11, 28:34] = 1
    label[30:34, 30:34] = 2
    visible = np.ones((40, 40), bool)
    visible[20:23, :] = False
    return z, label, visible


def test_four_regions_from_truth():
    z, label, visible = _regions_case()
    regions = regions_from_truth(z, label, visible, 1.0, RegionRule(flat_max_deg=10, steep_min_deg=25))
    assert list(regions) == list(REGIONS)
    stack = np.stack(list(regions.values())).astype(int)
    assert stack.sum(0).max() == 1  # disjoint
    assert regions["buildings"].sum() == 36 and regions["buildings"][5:11, 28:34].all()
    assert regions["mismatch_prone"][30:34, 30:34].all() and regions["mismatch_prone"][20:23].all()
    assert regions["mismatch_prone"].sum() == 16 + 3 * 40
    # the 45 deg plane is steep up to the ridge (central difference there: 0.5 m/m, 26.6 deg), the flat half is not
    assert regions["steep"][:20, :20].all() and regions["steep"][:, 20:].sum() == 0
    # flat: the east half minus the building, the tree, the hidden band, and the column next to the ridge
    assert regions["flat"][0, 21:].all() and not regions["flat"][:, :20].any()
    with pytest.raises(ValueError, match="shapes differ"):
        regions_from_truth(z, label[:-1], visible, 1.0)


def test_region_tables_score_each_region_on_its_common_cells():
    z, label, visible = _regions_case()
    regions = regions_from_truth(z, label, visible, 1.0)
    rng = np.random.default_rng(0)
    good = z + rng.normal(0, 0.1, z.shape)
    bad_on_roofs = good.copy()
    bad_on_roofs[regions["buildings"]] += 5.0
    holes = good.copy()
    holes[:2, :] = np.nan  # removes 2 rows of the steep and flat regions from every table
    tables = compare_by_region({"good": good, "roofs": bad_on_roofs, "holes": holes}, z, regions)
    assert list(tables) == list(REGIONS)
    b = tables["buildings"]["scores"]
    assert b["roofs"]["median"] == pytest.approx(5.0, abs=0.1) and abs(b["good"]["median"]) < 0.1
    assert tables["steep"]["common"]["count"] == regions["steep"].sum() - 2 * 20
    for region in ("steep", "flat", "mismatch_prone"):
        assert tables[region]["scores"]["roofs"]["rmse"] == pytest.approx(tables[region]["scores"]["good"]["rmse"])


def test_report_has_region_table_and_blunder_columns():
    ref, a, b = _case()
    scores, common = _score_tables(ref, {"srcnn": a, "vdsr": b}, {"vs_truth_visible": (ref, None)})
    z, label, visible = _regions_case()
    regions = regions_from_truth(z, label, visible, 1.0)
    metrics = {
        "name": "t", "input": "x", "sr": {"scale": 2, "degrade": "bicubic", "bit_depth": 12, "border": 2},
        "grid": {"resolution": 0.5, "width": 4, "height": 5},
        "hr": scores["hr"], "methods": {"srcnn": {**scores["srcnn"]}, "vdsr": {**scores["vdsr"]}},
        "common": common, "timings": {"hr": 1.0},
        "regions": {"rule": "flat < 10 deg", "dsms": ["srcnn"], "tables": compare_by_region({"srcnn": z + 0.2}, z, regions)},
    }
    report = markdown_report(metrics)
    assert "| Method | RMSE (m) | MRE (%) | NMAD (m) | Blunders (%) | Completeness (%) |" in report
    assert "**Table 4.** Four-region breakdown" in report
    assert f"| Buildings (roofs) | {regions['buildings'].sum()} | 0.200 / 0.000 / 0.0 |" in report


def test_blunder_map_marks_the_blunders_red(tmp_path):
    import matplotlib.image as mpimg

    h, ref, truth = _blunder_case()
    h = np.kron(h, np.ones((8, 8)))  # 80 x 80 cells: blunder blocks large enough to see
    ref = np.kron(ref, np.ones((8, 8)))
    clean = ref + np.random.default_rng(0).normal(0, 0.1, ref.shape)  # normal errors: 0.27 % beyond 3 NMAD
    path = blunder_map({"srcnn": h, "clean": clean},
                       ref, np.ones(ref.shape, bool), 1.0, tmp_path / "b.png", "test")
    img = mpimg.imread(path)[..., :3]
    red = (img[..., 0] > 0.8) & (img[..., 1] < 0.2) & (img[..., 2] < 0.2)
    half = img.shape[1] // 2
    assert red[:, :half].sum() > 4 * 8 * 8 * 0.5  # the four blunder blocks in the first panel
    assert red[:, half:].sum() < red[:, :half].sum() / 4  # 17 of 6400 cells, plus the legend swatch
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.png"]
