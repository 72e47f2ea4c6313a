"""``pipeline: dsm``: views (or a synthetic scene) to a DSM, its exports,
its accuracy against a reference and ``metrics.json``; optionally the
images oriented first (``orient:``)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Literal, Optional

from pydantic import Field

from tiledsm.cluster import ClusterConfig
from tiledsm.orient.spec import OrientSpec
from tiledsm.recipes import ClusterSpec, GridSpec, InputSpec, MatchSpec, OutputSpec, StrictModel, option
from tiledsm.workflows.common import completeness, grid_chunk, log, write_dsm_products, write_json

__all__ = ["DSMRecipe", "run_dsm"]


class DSMRecipe(StrictModel):
    """``pipeline: dsm`` — views (or a synthetic scene) to a DSM with a report."""

    pipeline: Literal["dsm"]
    name: str = "dsm"
    input: InputSpec
    grid: GridSpec = Field(GridSpec(), json_schema_extra=option("--like/--bounds"))
    match: MatchSpec = MatchSpec()
    cluster: ClusterSpec = ClusterSpec()
    output: OutputSpec = Field(OutputSpec(), json_schema_extra=option("--geoid"))  # the command's only output option
    orient: Optional[OrientSpec] = Field(None, description="orient the images first (GCPs, reference DEM); the DSM uses the corrected RPCs",
                                         json_schema_extra=option(None))  # recipes only: `tiledsm orient`'s options


def run_dsm(
    recipe: DSMRecipe, out: Path, cluster: ClusterConfig | None = None, overwrite: bool = False, plan=None
) -> dict:
    """Views (or a synthetic scene) -> DSM products and metrics.

    ``plan`` (:func:`tiledsm.dsm.plan.plan_dsm`) carries the opened views, tie
    points and lazy DSM; without it (or for a synthetic scene, made here
    first) the run plans itself. Its warnings, and a low completeness, go
    to ``metrics.json`` (``warnings``).
    """
    from tiledsm.dsm.plan import plan_dsm
    from tiledsm.plan import LOW_COMPLETENESS, Limits, new_plan

    cluster = cluster or recipe.cluster.config()
    t_start = time.perf_counter()
    inp = recipe.input
    truth_mask = None
    orient_doc = None
    if recipe.orient is not None and inp.images is not None:
        # orient first; the DSM uses the corrected copies (a plan made on the original images is stale)
        from tiledsm.orient.step import orient_for_recipe

        images, rpcs, orient_doc = orient_for_recipe(inp.images, inp.rpcs, recipe.orient, out / "orient", overwrite=overwrite)
        recipe = recipe.model_copy(update={"input": inp.model_copy(update={"images": images, "rpcs": rpcs})})
        inp, plan = recipe.input, None
    limits = plan.limits if plan is not None else Limits()
    if inp.synth is not None:
        from tiledsm.synth import make_scene

        sy = inp.synth
        log.info("making synthetic scene %s", sy.model_dump())
        scene = make_scene(out / "scene", size=sy.size, gsd=sy.gsd, bh=sy.bh, seed=sy.seed, views=sy.views, event=False)
        truth_mask = getattr(scene, "visible_mask", None)
        views_recipe = recipe.model_copy(update={"input": InputSpec(
            images=[str(p) for p in scene.views], reference=str(scene.truth_dsm))})
        plan = plan_dsm(new_plan("run", out, cluster, limits=limits), views_recipe, cluster, overwrite=overwrite)
    elif plan is None or plan.prepared is None:
        plan = plan_dsm(new_plan("run", out, cluster, limits=limits), recipe, cluster, overwrite=overwrite)
    prep = plan.prepared
    reference, report = prep.reference, prep.report
    scores: dict = {}
    warnings = list(plan.warnings)

    def score_completeness() -> None:
        """Completeness, read from the finished store while its exports are written."""
        from tiledsm.io import open_product

        height = open_product(out / "dsm.zarr")["height"]
        # lazy: the client never holds the whole DSM for this
        scores["completeness"], scores["completeness_in_footprint"] = completeness(height, prep.views, prep.h_range)
        if scores["completeness_in_footprint"] < LOW_COMPLETENESS:
            warnings.append(
                f"low completeness: {scores['completeness_in_footprint']:.0%} of the cells seen by every view have "
                f"a height (expected >= {LOW_COMPLETENESS:.0%}; check the height range and the images' overlap)"
            )
            log.warning(warnings[-1])

    def score_reference() -> None:
        """The metrics against the reference, chunk by chunk from the
        finished store (the client never holds the whole DSM or reference),
        once the exports are written (run beside them, the fit's windows and
        the histograms added to the COG's memory), on as many threads of
        this process as the run has workers (not one per core: each thread
        holds its chunks and partial histograms)."""
        from tiledsm.compare.accuracy import reference_accuracy
        from tiledsm.io import open_product

        height = open_product(out / "dsm.zarr")["height"]
        scores["reference"] = str(reference)
        scores["vs_reference"], error = reference_accuracy(height, reference, chunks=grid_chunk(height),
                                                           coregister=True)
        if recipe.output.quicklook:
            from tiledsm.quicklook import quicklook

            r0, r1, c0, c1 = error.attrs["window"]
            quicklook(error, out / "dsm_error.png", kind="difference", title="DSM - reference (m)",
                      dsm=height[r0:r1, c0:c1])
        if truth_mask is not None:
            scores["vs_reference_visible"], _ = reference_accuracy(
                height, reference, truth_mask, chunks=grid_chunk(height)
            )

    timings = write_dsm_products(
        prep.ds, out, cluster=cluster, cog=recipe.output.cog, quicklook=recipe.output.quicklook, overwrite=overwrite,
        alongside=score_completeness,
    )
    if reference:
        import dask

        t_score = time.perf_counter()
        with dask.config.set(scheduler="threads", num_workers=cluster.local_workers):
            score_reference()
        timings["score_s"] = time.perf_counter() - t_score
    metrics: dict = {"pipeline": "dsm", "report": report, "timings": timings}
    if orient_doc is not None:
        metrics["orient"] = orient_doc
    metrics.update(scores)
    metrics["warnings"] = warnings
    metrics["timings"]["total_s"] = time.perf_counter() - t_start
    metrics["output_mpx_per_s"] = prep.ds["height"].size / 1e6 / max(timings["match_s"], 1e-9)
    write_json(metrics, out / "metrics.json")
    log.info("metrics: %s", json.dumps(metrics))
    return metrics
