"""benchmarks/dsm_paired.py --append: rows of other cases or other
baselines are kept, a row measured again against the same baseline is
replaced."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.dsm_paired import merge_rows  # noqa: E402


def _row(case, commit=None, wall=1.0):
    r = {"case": case, "a_wall_s_median": wall}
    if commit:
        r["baseline"] = {"rev": commit, "commit": commit}
    return r


def test_append_keeps_other_baselines_and_replaces_the_same():
    # a file from before rows named their baseline: it is at the top
    earlier = {"when": "t0", "command": "first", "baseline": {"rev": "X", "commit": "X"},
               "rows": [_row("synth16384", wall=300.0), _row("synth4096", wall=30.0)]}
    rows, command = merge_rows(earlier, [_row("synth4096", "Y", wall=29.0)])
    assert [(r["case"], r["baseline"]["commit"], r["a_wall_s_median"]) for r in rows] == [
        ("synth16384", "X", 300.0), ("synth4096", "X", 30.0), ("synth4096", "Y", 29.0)]
    assert rows[0]["when"] == "t0" and command == "first"

    again = {"when": "t1", "command": "second", "rows": rows}
    rows2, command2 = merge_rows(again, [_row("synth4096", "X", wall=28.0)])
    assert [(r["case"], r["baseline"]["commit"], r["a_wall_s_median"]) for r in rows2] == [
        ("synth16384", "X", 300.0), ("synth4096", "Y", 29.0), ("synth4096", "X", 28.0)]
    assert rows2[0]["when"] == "t0" and command2 == "second"


def test_append_to_nothing_kept_names_no_earlier_command():
    earlier = {"when": "t0", "command": "first", "rows": [_row("s2p", "X")]}
    rows, command = merge_rows(earlier, [_row("s2p", "X", wall=2.0)])
    assert [r["a_wall_s_median"] for r in rows] == [2.0] and command is None
