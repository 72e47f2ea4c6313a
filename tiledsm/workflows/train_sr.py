"""``pipeline: train_sr``: train a super-resolution network; the card
(measured steps, time, PSNR) is the run's ``metrics.json``."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import field_validator

from tiledsm.cluster import ClusterConfig
from tiledsm.recipes import StrictModel
from tiledsm.workflows.common import write_json

__all__ = ["TrainSRRecipe", "run_train_sr"]


class TrainSRRecipe(StrictModel):
    """``pipeline: train_sr`` — train a super-resolution network; ``train``
    holds the fields of :class:`tiledsm.sr.train.TrainConfig`."""

    pipeline: Literal["train_sr"]
    name: str = "train_sr"
    train: dict[str, Any]

    @field_validator("train")
    @classmethod
    def _valid_config(cls, value: dict[str, Any]) -> dict[str, Any]:
        import dataclasses

        from tiledsm.sr.train import TrainConfig

        known = {f.name for f in dataclasses.fields(TrainConfig)}
        unknown = sorted(set(value) - known)
        if unknown:
            raise ValueError(f"unknown field(s) {unknown}; known: {sorted(known)}")
        return value


def run_train_sr(recipe, out: Path, cluster: ClusterConfig | None = None, overwrite: bool = False) -> dict:
    """Train an SR network; the card (measured steps, time, PSNR) is the metrics."""
    from tiledsm.sr.train import TrainConfig, train

    values = dict(recipe.train)
    for key in ("data_dirs", "blur_range", "noise_range"):
        if values.get(key) is not None:
            values[key] = tuple(values[key])
    values.setdefault("out", str(out / f"{values.get('model', 'model')}.pt"))
    card = train(TrainConfig(**values))
    metrics = {"pipeline": "train_sr", "card": card}
    write_json(metrics, out / "metrics.json")
    return metrics
