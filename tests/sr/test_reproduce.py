"""Reproducibility of the shipped SRCNN (issue 15): retraining it from
``recipes/train_sr.yaml`` with the recipe's seed gives weights whose held-out
PSNR is within 0.05 dB of what the shipped card records.

Oracle: the card written when the shipped weights were trained, on the same
images (checked by their sha256) and the same step count. About 4 minutes on
one core: the whole schedule, since a shortened one would not test the
shipped weights.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import require_shared
from tiledsm.sr.registry import load_pretrained
from tiledsm.sr.train import config_from_yaml, train

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_srcnn_retrained_from_the_recipe_matches_the_shipped_card(tmp_path):
    sr_train = require_shared("sr_train")
    config = config_from_yaml(REPO / "recipes" / "train_sr.yaml", out=str(tmp_path / "srcnn_x2.pt"),
                              data_dirs=(str(sr_train),))
    shipped = load_pretrained("srcnn", 2).card
    assert shipped["config"]["seed"] == config.seed and shipped["steps"] == config.steps and shipped["finished"]
    card = train(config, log=lambda m: None)
    assert card["finished"] and card["data"] == shipped["data"]  # same images, same checksums
    assert card["params"] == shipped["params"]
    for name, psnr in shipped["heldout_psnr_db"].items():
        assert card["heldout_psnr_db"][name]["model"] == pytest.approx(psnr["model"], abs=0.05), name
        assert card["heldout_psnr_db"][name]["bicubic"] == pytest.approx(psnr["bicubic"], abs=1e-6), name
