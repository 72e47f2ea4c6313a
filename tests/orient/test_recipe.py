"""The recipe section ``orient:`` (:mod:`tiledsm.orient.spec`) and its step
(:mod:`tiledsm.orient.step`): validation, :func:`orient_for_recipe` on a rendered pair with injected biases and a
coarse reference DEM (oracle: the scene's truth DSM and true cameras),
reuse of its products, the stable-ground exclusion, and the deformation
recipe's joint pre/post orientation."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from pydantic import ValidationError
from pyproj import Transformer

from tiledsm.io.cameras import find_camera
from tiledsm.orient.adjust import intersect
from simulate import project_all
from tiledsm.orient.spec import OrientSpec
from tiledsm.orient.step import orient_for_recipe, polygon_exclusion


def test_spec_validation():
    assert OrientSpec().model == None  # noqa: E711  (None: chosen by point count)
    assert OrientSpec(dem="a.tif", geoid="g.gtx", model="shift").model == "shift"
    assert OrientSpec().extractor == "structural" and OrientSpec(extractor="features").extractor == "features"
    for bad, word in (({"geoid": "g.gtx"}, "dem"), ({"model": "poly"}, "model"), ({"gcp": "x.csv"}, "gcp"),
                      ({"extractor": "sift"}, "extractor"), ({"datum": "median"}, "datum"),
                      ({"tie_sigma_px": 0}, "tie_sigma_px"), ({"adjust": {"loss": "l2"}}, "adjust.loss"),
                      ({"tracks": {"structural": {"template": 14}}}, "tracks.structural.template"),
                      ({"tracks": {"tile": 256}}, "tracks.tile")):
        with pytest.raises(ValidationError, match=word):
            OrientSpec(**bad)
    # the advanced parameters: nested, recipe only, read by the functions as they are
    spec = OrientSpec.model_validate({"tile": 256, "adjust": {"dem_sigma_m": 5.0},
                                      "tracks": {"p2l": {"k": 3.0}, "structural": {"min_ncc": 0.5}}})
    assert (spec.tile, spec.adjust.dem_sigma_m, spec.tracks.p2l.k, spec.tracks.structural.min_ncc) == (256, 5.0, 3.0, 0.5)
    assert spec.adjust.max_rounds == 6 and spec.tracks.structural.template == 15  # the others at their defaults


def test_datum_names_are_the_rules():
    from typing import get_args

    from tiledsm.orient.datum import DATUMS

    assert set(get_args(OrientSpec.model_fields["datum"].annotation)) == set(DATUMS)


def test_deformation_spec_needs_joint_for_points():
    from tiledsm.workflows.deformation import DeformationOrientSpec, DeformationRecipe

    assert DeformationOrientSpec().joint is True
    with pytest.raises(ValidationError, match="joint"):
        DeformationOrientSpec(joint=False, gcps="g.csv")
    r = DeformationRecipe.model_validate({"pipeline": "deformation", "input": {"synth": {"size": 128}},
                                          "orient": {"dem": "srtm.tif", "joint": True}})
    assert r.orient.dem == "srtm.tif" and isinstance(r.orient, OrientSpec)


def test_polygon_exclusion(tmp_path):
    ring = [[5.0, 44.0], [5.1, 44.0], [5.1, 44.1], [5.0, 44.1], [5.0, 44.0]]
    hole = [[5.04, 44.04], [5.06, 44.04], [5.06, 44.06], [5.04, 44.06], [5.04, 44.04]]
    doc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [ring, hole]}}]}
    (tmp_path / "m.geojson").write_text(json.dumps(doc))
    ex = polygon_exclusion(tmp_path / "m.geojson")
    lon = np.array([5.01, 5.05, 5.2, 5.09])
    lat = np.array([44.01, 44.05, 44.05, 44.09])
    assert ex(lon, lat).tolist() == [True, False, False, True]


def _coarse_dem(truth_path, out, k):
    """The truth DSM block-averaged to ``k x k`` cells (a coarse DSM like SRTM)."""
    from rasterio.transform import Affine

    with rasterio.open(truth_path) as ds:
        z = ds.read(1)
        zz = z.reshape(z.shape[0] // k, k, z.shape[1] // k, k).mean(axis=(1, 3))
        prof = dict(driver="GTiff", width=zz.shape[1], height=zz.shape[0], count=1, dtype="float32", crs=ds.crs,
                    transform=ds.transform @ Affine.scale(k))
    with rasterio.open(out, "w", **prof) as d:
        d.write(zz.astype(np.float32), 1)
    return out


def _ground_truth_points(info, n=400, seed=0):
    """lon, lat, h of random visible ground cells of the truth DSM."""
    with rasterio.open(info.truth_dsm) as ds, rasterio.open(info.visible_mask) as vm, \
            rasterio.open(info.truth_label) as lb:
        z, vis, lab, tr, crs = ds.read(1), vm.read(1), lb.read(1), ds.transform, ds.crs
    ii, jj = np.nonzero((vis == 1) & (lab == 0) & np.isfinite(z))
    pick = np.random.default_rng(seed).choice(ii.size, n, replace=False)
    x, y = tr @ (jj[pick] + 0.5, ii[pick] + 0.5)
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
    return np.asarray(lon), np.asarray(lat), z[ii[pick], jj[pick]].astype(float)


def _read(path) -> np.ndarray:
    with rasterio.open(path) as ds:
        return ds.read(1).astype(float)


def _height_bias(rpcs, true, lon, lat, h) -> float:
    p = project_all(true, lon, lat, h)
    v, n = p.shape[:2]
    g, _ = intersect(rpcs, np.repeat(np.arange(v), n), np.tile(np.arange(n), v), p[:, :, 0].ravel(),
                     p[:, :, 1].ravel(), n, h0=h)
    return float(np.median(g[:, 2] - h))


def test_orient_for_recipe(scene2, tmp_path):
    """Every field of ``orient:`` (4 GCPs, check points, the truth averaged
    to 8 m as DEM, the affine model): the corrected copies' own RPCs match
    the true cameras within 0.1 px and intersect true ground
    correspondences with a height bias <= 0.15 m (injected: ~8 m; the
    averaged DEM pulls against the GCPs a little: 0.04 px without it);
    a second call reuses the products."""
    from orient_cases import write_gcp_files

    info, true, biased, h, root = scene2
    names = [p.name for p in biased]
    write_gcp_files(true, names, tmp_path)
    dem = _coarse_dem(info.truth_dsm, tmp_path / "dem8.tif", 16)
    spec = OrientSpec(gcps=str(tmp_path / "gcps.csv"), check_points=str(tmp_path / "checks.csv"), dem=str(dem),
                      model="affine")
    images, rpcs, doc = orient_for_recipe(biased, None, spec, tmp_path / "orient")
    assert rpcs is None and [p.split("/")[-1] for p in images] == names
    after = [find_camera(p)[0] for p in images]
    lon, lat, hh = _ground_truth_points(info)
    d = project_all(after, lon, lat, hh) - project_all(true, lon, lat, hh)
    vs_true = np.sqrt(np.mean(np.sum(d**2, axis=-1), axis=1))
    before_b = _height_bias([find_camera(p)[0] for p in biased], true, lon, lat, hh)
    after_b = _height_bias(after, true, lon, lat, hh)
    print("vs true px", vs_true, "check px", doc["check_rms_px"], "height bias", before_b, "->", after_b)
    assert doc["images"][0]["model"] == "affine" and doc["dem"]["n_used"] > 50
    assert np.all(vs_true < 0.1) and doc["check_rms_px"]["after"] < 0.1 < 2.5 < doc["check_rms_px"]["before"]
    assert abs(before_b) > 5.0 and abs(after_b) <= 0.15
    stamp = (tmp_path / "orient" / "orient.json").stat().st_mtime_ns
    again, _, doc2 = orient_for_recipe(biased, None, spec, tmp_path / "orient")
    assert again == images and doc2 == json.loads((tmp_path / "orient" / "orient.json").read_text())
    assert (tmp_path / "orient" / "orient.json").stat().st_mtime_ns == stamp  # reused, not redone


@pytest.mark.slow
def test_deformation_joint_orientation(tmp_path):
    """``orient: {joint: true}`` on a synthetic event with biased post-event
    cameras: pre- and post-event images in one block, tie points outside
    the exclusion polygons. Oracle: true correspondences of stable ground
    (pre position ``q - (dx, dy)`` at ``f_post(q) - dz``, post position
    ``q`` at ``f_post(q)``, the event's convention) intersect in the four
    corrected views with a residual << the injected 2-3 px."""
    from orient_cases import BIASES

    from simulate import biased_copies
    from tiledsm.synth import make_scene
    from tiledsm.workflows.deformation import DeformationOrientSpec, _orient_epochs
    from tiledsm.workflows.fault import event_exclusion_polygons, write_geojson

    scene = make_scene(tmp_path / "scene", size=256, views=2, seed=3, event=True, chunk=256, workers=1)
    ev = scene.event
    pre_true = [find_camera(p)[0] for p in scene.views]
    post_true = [find_camera(p)[0] for p in ev["post_views"]]
    h = (pre_true[0].height_off - pre_true[0].height_scale, pre_true[0].height_off + pre_true[0].height_scale)
    post_biased = biased_copies(ev["post_views"], post_true, BIASES[1:3], tmp_path / "biased", h)
    feats, _ = event_exclusion_polygons(ev["params"], scene.origin, scene.grid.width * scene.grid.resolution)
    mask = write_geojson(feats, scene.grid.crs, tmp_path / "stable_mask.geojson")
    pre_in, post_in, rep = _orient_epochs(DeformationOrientSpec(), ([str(p) for p in scene.views], None),
                                          ([str(p) for p in post_biased], None), tmp_path / "run", str(mask), False)
    assert rep["joint"] and pre_in[1] is None and len(post_in[0]) == 2
    assert rep["n_tracks_excluded"] > 0 and rep["n_tracks"] > 50
    cams = [find_camera(p)[0] for p in (*pre_in[0], *post_in[0])]

    # stable ground cells of the post-event truth (outside the exclusion polygons)
    with rasterio.open(ev["post_dsm"]) as ds:
        zpost, tr, crs = ds.read(1).astype(float), ds.transform, ds.crs
    dx, dy, dz = (_read(ev[k]) for k in ("dx", "dy", "dz"))
    ii, jj = np.nonzero(np.isfinite(zpost))
    pick = np.random.default_rng(0).choice(ii.size, 3000, replace=False)
    ii, jj = ii[pick], jj[pick]
    x, y = tr @ (jj + 0.5, ii + 0.5)
    to_ll = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    lon, lat = to_ll.transform(x, y)
    keep = ~polygon_exclusion(mask)(np.asarray(lon), np.asarray(lat))
    ii, jj, x, y = ii[keep][:300], jj[keep][:300], x[keep][:300], y[keep][:300]
    lon_post, lat_post = to_ll.transform(x, y)
    lon_pre, lat_pre = to_ll.transform(x - dx[ii, jj], y - dy[ii, jj])
    hp = zpost[ii, jj]
    meas = np.concatenate([project_all(pre_true, lon_pre, lat_pre, hp - dz[ii, jj]),
                           project_all(post_true, lon_post, lat_post, hp)])
    n = hp.size

    def rms(rpcs):
        _, res = intersect(rpcs, np.repeat(np.arange(4), n), np.tile(np.arange(n), 4), meas[:, :, 0].ravel(),
                           meas[:, :, 1].ravel(), n, h0=hp)
        return float(np.sqrt(np.nanmean(np.sum(res**2, axis=1))))

    before = rms(pre_true + [find_camera(p)[0] for p in post_biased])
    after = rms(cams)
    print("pre+post relative RMS before", before, "after", after, "excluded", rep["n_tracks_excluded"],
          "of", rep["n_tracks"])
    assert before > 1.0 and after < 0.1


@pytest.mark.slow
def test_dsm_recipe_orients_first(scene2, tmp_path):
    """``pipeline: dsm`` with ``orient:`` (4 GCPs) run as a user runs it:
    the images are oriented into ``orient/``, the DSM is matched on the
    corrected copies, and its heights sit on the truth (median within
    0.08 m) where the biased cameras put them metres off."""
    import subprocess
    import sys

    import yaml
    from orient_cases import write_gcp_files

    info, true, biased, h, root = scene2
    write_gcp_files(true, [p.name for p in biased], tmp_path)
    rec = {"pipeline": "dsm", "input": {"images": [str(p) for p in biased], "reference": str(info.truth_dsm)},
           "grid": {"like": str(info.truth_dsm), "chunk": 256}, "orient": {"gcps": str(tmp_path / "gcps.csv"), "model": "affine"},
           "cluster": {"scheduler": "synchronous"}, "output": {"cog": False, "quicklook": False}}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(rec))
    r = subprocess.run([sys.executable, "-m", "tiledsm", "run", str(tmp_path / "r.yaml"), "--out", str(tmp_path / "o"),
                        "--no-progress"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["orient"]["gcp_rms_px"]["after"] < 0.05 < 3.0 < m["orient"]["gcp_rms_px"]["before"]
    from tiledsm.io import open_product

    views = open_product(tmp_path / "o" / "dsm.zarr").attrs["views"]
    assert [Path(v).parent for v in views] == [tmp_path / "o" / "orient"] * 2, views
    # measured: median -0.05 m; GCP residuals 3.90 -> 0.036 px
    assert abs(m["vs_reference"]["median"]) < 0.08, m["vs_reference"]
