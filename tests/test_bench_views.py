"""benchmarks/views.py: the cases are scored against the truth on the cells
where every case has a height, each with its own completeness. Oracle: small
grids with known holes and known errors."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import tiledsm.workflows.sr_dsm  # noqa: F401  (imported lazily by the helpers: xarray, dask; load it at collection)

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.views import markdown_table, score_cases  # noqa: E402


def _scene():
    """Truth on 6 x 6 cells, the last column invisible; a 2-view DSM with a
    hole at (1, 1) and 0.3 m errors, a 3-view DSM complete with 0.1 m errors
    except a 40 m blunder at (1, 1)."""
    truth = np.linspace(50.0, 80.0, 36).reshape(6, 6)
    visible = np.ones(truth.shape, bool)
    visible[:, 5] = False
    two = truth + 0.3
    two[1, 1] = np.nan
    three = truth - 0.1
    three[1, 1] += 40.0
    return {"views 0-1": two, "3 views": three}, truth, visible


def test_cases_are_scored_on_the_common_cells():
    heights, truth, visible = _scene()
    rows, common = score_cases(heights, truth, visible)
    assert (common["count"], common["cells"]) == (29, 30)
    assert common["dsms"] == ["views 0-1", "3 views"]
    # the 3-view blunder lies in the 2-view hole: excluded from the 3-view scores
    assert rows["3 views"]["rmse_m"] == pytest.approx(0.1) and rows["3 views"]["median_m"] == pytest.approx(-0.1)
    assert rows["views 0-1"]["rmse_m"] == pytest.approx(0.3)
    assert rows["views 0-1"]["scored"] == rows["3 views"]["scored"] == 29
    # own completeness on the 30 visible cells
    assert rows["views 0-1"]["completeness"] == pytest.approx(29 / 30) and rows["views 0-1"]["valid"] == 29
    assert rows["3 views"]["completeness"] == pytest.approx(1.0) and rows["3 views"]["valid"] == 30


def test_markdown_table_names_the_common_cells():
    heights, truth, visible = _scene()
    scores, common = score_cases(heights, truth, visible)
    rows = [{"case": name, "match_s": 1.5, **scores[name]} for name in heights]
    table = markdown_table(rows, common)
    print(table)
    assert table.startswith("Scored on 29 common cells (96.7 % of the 30 cells of the visible truth)")
    assert "| views 0-1 | 0.000 | 0.300 | +0.300 | 96.7 % | 1.5 |" in table
    assert "| 3 views | 0.000 | 0.100 | -0.100 | 100.0 % | 1.5 |" in table
