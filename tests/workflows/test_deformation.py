"""The deformation workflow end to end: a synthetic earthquake seen by a pre-
and a post-event stereo pair, the vertical displacement and the fault throw
recovered against the known truth; bad recipes and non-overlapping pairs."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from tiledsm.cluster import ClusterConfig
from tiledsm.errors import NoOverlapError, RecipeError, TiledsmError
from tiledsm.pipelines import load_recipe, run_recipe
from tiledsm.workflows.fault import Fault, event_exclusion_polygons, throw_across

CLUSTER = ClusterConfig(workers=2, progress=False)

# issue 5 acceptance bars
RMSE_MAX, THROW_TOL = 0.5, 0.3


def _recipe(tmp: Path, **fields) -> Path:
    doc = {
        "pipeline": "deformation",
        "input": {"synth": {"size": 512, "gsd": 0.5, "bh": 0.4, "seed": 0, "event": True}},
        "grid": {"chunk": 256},
        "compare": {"coreg": "nuth_kaab", "chunk": 256},
    }
    doc.update(fields)
    path = tmp / "deformation.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.fixture(scope="module")
def event_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("deformation")
    out = tmp / "run"
    metrics = run_recipe(load_recipe(_recipe(tmp)), out, CLUSTER)
    return out, metrics


def _evaluated(out: Path) -> dict:
    """``tiledsm evaluate OUT``: the dh scores against the run's synthetic scene."""
    from tiledsm.cli import main

    assert main(["evaluate", str(out)]) == 0
    return json.loads((out / "evaluation.json").read_text())["scores"]["dh"]


# ---------------------------------------------------------------------------- synthetic event from stereo pairs
@pytest.mark.slow
def test_event_from_stereo_pairs_recovers_displacement_and_throw(event_run):
    out, m = event_run
    assert "truth" not in m  # the run grades nothing: tiledsm evaluate does
    t = _evaluated(out)
    err = t["dh_error_visible_ground"]
    print(f"deformation 512: coreg error {t['coregistration_error']}, rmse {err['rmse']:.3f} m, "
          f"throw {t['throw']['recovered']:.3f} vs {t['throw']['truth']:.3f} m")
    assert err["rmse"] <= RMSE_MAX and err["count"] > 0.5 * 512 * 512
    assert abs(t["throw"]["error"]) <= THROW_TOL
    assert abs(t["throw"]["recovered"] - t["throw"]["nominal"]) <= THROW_TOL
    # the stable terrain left by the rupture mask is one rigid block: its motion is found
    ce = t["coregistration_error"]
    assert abs(ce["dx_px"]) < 0.1 and abs(ce["dy_px"]) < 0.1 and abs(ce["dz"]) < 0.05
    assert m["stable_terrain"]["statistics"]["nmad"] < 0.1


@pytest.mark.slow
def test_event_products_and_resolved_recipe(event_run):
    out, m = event_run
    for p in ("pre/dsm.zarr", "pre/dsm.tif", "post/dsm.zarr", "post/dsm.tif", "compare/dh.zarr", "compare/dh.tif",
              "compare/dh.png", "compare/report.html", "compare/metrics.json", "scene/stable_mask.geojson",
              "metrics.json", "recipe.resolved.yaml", "run.log"):
        assert (out / p).exists(), p
    assert json.loads((out / "metrics.json").read_text())["fault"] == json.loads(json.dumps(m["fault"]))
    # the post DSM lies on the pre DSM's grid
    import rasterio

    with rasterio.open(out / "pre/dsm.tif") as a, rasterio.open(out / "post/dsm.tif") as b:
        assert a.transform == b.transform and a.shape == b.shape and a.crs == b.crs
    assert not list(out.glob("compare/.compare-staging-*"))


@pytest.mark.slow
def test_event_without_coregistration_in_the_plain_truth_frame(event_run, tmp_path):
    """The pairs share their RPCs: with coreg 'none' dh is the absolute truth dh."""
    out, _ = event_run
    run2 = tmp_path / "run"
    run2.mkdir()
    for name in ("pre", "post"):  # reuse the finished DSM stores (resumable: nothing recomputed)
        shutil.copytree(out / name, run2 / name)
    recipe = load_recipe(_recipe(tmp_path, compare={"coreg": "none", "chunk": 256}))
    run_recipe(recipe, run2, CLUSTER)
    t = _evaluated(run2)
    assert t["frame"] == "plain truth dh" and not (run2 / "scene" / "stable_mask.geojson").exists()
    assert t["dh_error_visible_ground"]["rmse"] <= RMSE_MAX
    assert abs(t["throw"]["error"]) <= THROW_TOL


# ---------------------------------------------------------------------------- pure helpers
def test_throw_across_a_step():
    x = np.arange(200) * 0.5
    y = np.arange(100)[::-1] * 0.5
    fault = Fault((50.0, 0.0), (0.0, 1.0))  # north-going trace at x = 50: right = east
    d = fault.signed_distance(x, y)
    dh = np.where(d > 0, 0.7, -1.3) + np.random.default_rng(0).normal(0, 0.05, d.shape)
    dh[np.abs(d) < 2] = np.nan
    r = throw_across(dh, d, (3.0, 20.0))
    assert r["throw"] == pytest.approx(2.0, abs=0.02) and r["n_left"] > 0 and r["n_right"] > 0
    with pytest.raises(TiledsmError, match="no valid dh in the strips"):
        throw_across(dh, d + 1000.0, (3.0, 20.0))


def test_exclusion_polygons_keep_the_block_without_uplift():
    from tiledsm.synth import EventParams

    ev = EventParams.for_extent(384.0)
    feats, kept = event_exclusion_polygons(ev, (0.0, 0.0), 384.0)
    assert [f["properties"]["name"] for f in feats] == ["fault zone", "uplift", "block holding the uplift"]
    side = np.dot(np.asarray(ev.uplift_center) - np.asarray(ev.fault_point), ev.normal)
    assert kept == (-1 if side > 0 else 1)


# ---------------------------------------------------------------------------- bad input
def test_wrong_recipe_fields_are_named(tmp_path):
    cases = [
        ({"compare": {"coreg": "icp"}}, "compare.coreg"),
        ({"compare": {"chunck": 256}}, "compare.chunck"),
        ({"input": {"synth": {"size": 128, "event": False}}}, "input.synth.event"),
        ({"input": {"pre": {"images": ["a.tif", "b.tif"]}}}, "both 'pre' and 'post'"),
        ({"input": {"synth": {"size": 128}, "pre": {"images": ["a.tif", "b.tif"]}}}, "not both"),
        ({"input": {"pre": {"images": ["a.tif", "b.tif"], "rpcs": ["a.rpc"]}, "post": {"images": ["c.tif", "d.tif"]}}},
         "input.pre"),
        ({"fault": {"trace": [[5.2, 44.2], [5.21, 44.21]]}}, "'fault' is known for a synthetic event"),
    ]
    for fields, needle in cases:
        path = _recipe(tmp_path, **fields)
        with pytest.raises(RecipeError) as e:
            load_recipe(path)
        assert needle in str(e.value) and str(path) in str(e.value), (needle, str(e.value))


def test_relative_pair_paths_resolved(tmp_path):
    path = _recipe(tmp_path, input={"pre": {"images": ["a.tif", "b.tif"]}, "post": {"images": ["c.tif", "d.tif"]},
                                    "truth_dh": "dh.tif"}, compare={"stable_mask": "rupture.geojson"})
    r = load_recipe(path)
    assert r.input.pre.images == [str(tmp_path / "a.tif"), str(tmp_path / "b.tif")]
    assert r.input.truth_dh == str(tmp_path / "dh.tif")
    assert r.compare.stable_mask == str(tmp_path / "rupture.geojson")


def test_non_overlapping_pairs_are_refused_before_any_product(tmp_path):
    from tiledsm.synth import make_scene

    a = make_scene(tmp_path / "a", size=128, seed=1, workers=2)
    b = make_scene(tmp_path / "b", size=128, seed=2, center=(5.2, 44.21), workers=2)  # ~1.1 km north
    path = _recipe(tmp_path, input={"pre": {"images": [str(p) for p in a.views]},
                                    "post": {"images": [str(p) for p in b.views]}})
    out = tmp_path / "run"
    with pytest.raises(NoOverlapError) as e:
        run_recipe(load_recipe(path), out, CLUSTER)
    msg = str(e.value)
    assert str(b.views[0]) in msg and str(a.views[0]) in msg and "see no ground of the pre-event DSM grid" in msg
    # refused by the plan, before the run folder exists
    assert not out.exists()


def test_fault_trace_from_lonlat_points_right_is_east_when_going_north():
    from tiledsm.workflows.deformation import FaultSpec, fault_from_trace

    f = fault_from_trace(FaultSpec(trace=[(5.2, 44.19), (5.2, 44.21)]), "EPSG:32631")
    assert f.normal[0] > 0.99  # right of a north-going trace is east
    with pytest.raises(TiledsmError, match="are the same"):
        fault_from_trace(FaultSpec(trace=[(5.2, 44.2), (5.2, 44.2)]), "EPSG:32631")
