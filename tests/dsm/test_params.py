"""The DSM stage's parameters are pydantic models (:class:`DSMParams`,
:class:`SGVLLParams`, :class:`SearchParams`): checked where they are
built with the field's location, hashable, picklable, with one dask
token per value in any process, and the run fingerprint's content of the
dataclasses they replace (a DSM stored before resumes)."""

from __future__ import annotations

import copy
import json
import pickle
import subprocess
import sys

import pytest
from dask.base import tokenize
from pydantic import ValidationError

from tiledsm.dsm import DSMParams
from tiledsm.match.pyramid import SearchParams
from tiledsm.match.sgvll import SGVLLParams

#: ``dataclasses.asdict(DSMParams(levels=2, height_range=(300.0, 400.0)))`` of the dataclass
#: (main 321fc37), as the fingerprint's JSON stored it
DATACLASS_JSON = (
    '{"resolution": null, "crs": null, "chunk": 512, "levels": 2, "max_candidates": 128, "height_range": [300.0, 400.0], '
    '"height_margin": 10.0, "refine_steps": 4, "sweep_step_factor": 2.0, "relative_correction": true, "match": '
    '{"window": 5, "P1": 0.3, "P2": 2.0, "step_px": 0.5, "zncc_min": 0.25, "ratio_max": 0.98, "reject_edges": true, '
    '"speckle_size": 150, "speckle_slope": 60.0, "speckle_steps": 0.5, "proj_stride": 8, "lattice_steps": 16, '
    '"interpolation": "cubic", "invalid_cost": 1.0, "max_candidates": 2048, "ref_sigma": 3.0, "weight_pairs": true, '
    '"path_period": 64, "kernel": "fast", "device": "cpu"}, "search": {"smooth": 1.0, "fill_sigma": 4.0, '
    '"truncate": 3.0, "hole_factor": 3.0, "relative_labels": false}}'
)


def test_fingerprint_content_is_the_dataclass_one():
    params = DSMParams(levels=2, height_range=(300, 400))
    # the same content (fingerprints are compared as JSON objects, keys in any order)
    assert json.loads(json.dumps(params.model_dump())) == json.loads(DATACLASS_JSON)
    assert DSMParams.model_validate(json.loads(DATACLASS_JSON)) == params


@pytest.mark.parametrize("build, loc", [
    (lambda: DSMParams(chunk=33), ("chunk",)),
    (lambda: DSMParams(chunk=30), ("chunk",)),
    (lambda: DSMParams(levels=0), ("levels",)),
    (lambda: DSMParams(sweep_step_factor=0.5), ("sweep_step_factor",)),
    (lambda: DSMParams(match={"window": 4}), ("match", "window")),
    (lambda: SGVLLParams(P1=3.0), ("P2",)),  # above the default P2
    (lambda: SGVLLParams(kernel="nope"), ("kernel",)),
    (lambda: SGVLLParams(device="cuda"), ("device",)),  # the fast kernel runs on the CPU only
    (lambda: SGVLLParams(speckle_slope=90), ("speckle_slope",)),
    (lambda: SGVLLParams(interpolation="nearest"), ("interpolation",)),
    (lambda: SearchParams(smooth=5.0), ("fill_sigma",)),  # above the default fill_sigma
    (lambda: SearchParams(hole_factor=0.5), ("hole_factor",)),
])
def test_a_bad_value_is_refused_at_its_field(build, loc):
    with pytest.raises(ValidationError) as e:
        build()
    assert [err["loc"] for err in e.value.errors()] == [loc]


def test_a_misspelled_matching_parameter_is_named_with_the_valid_ones():
    with pytest.raises(ValidationError, match=r"unknown matching parameter\(s\) 'windw'; valid: window, P1, P2"):
        SGVLLParams(windw=5)


def test_hashable_picklable_one_token_per_value():
    p = DSMParams(levels=2, height_range=(300.0, 400.0), match=SGVLLParams(window=7))
    again = DSMParams.model_validate(p.model_dump())
    assert pickle.loads(pickle.dumps(p)) == p and hash(again) == hash(p) and {p: 1}[again] == 1
    assert tokenize(p) == tokenize(copy.deepcopy(p)) == tokenize(again)
    assert tokenize(p) != tokenize(p.model_copy(update={"levels": 3}))
    assert tokenize(p.match) != tokenize(SGVLLParams())


def test_token_is_the_same_in_another_process():
    code = ("from dask.base import tokenize; from tiledsm.dsm import DSMParams; "
            "print(tokenize(DSMParams(levels=2, height_range=(300.0, 400.0))))")
    tokens = {subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
              for _ in range(2)}
    assert tokens == {tokenize(DSMParams(levels=2, height_range=(300.0, 400.0)))}
