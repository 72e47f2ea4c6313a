"""Comparison statistics of tiledsm.workflows.sr_dsm: every compared DSM is
scored on the common cells (reference and every DSM valid), each with its own
completeness. Oracle: small grids with known holes and known errors."""

from __future__ import annotations

import numpy as np
import pytest

from tiledsm.workflows.sr_dsm import _score_tables
from tiledsm.workflows.sr_scores import (
    common_valid,
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


def test_report_without_common_block_still_renders():
    """Metrics written before common-cell scoring (no ``common``) still render."""
    truth, a, b = _case()
    metrics = _metrics(truth, {"bicubic": a}, {})
    del metrics["common"]
    assert "Scored on" not in markdown_report(metrics)
