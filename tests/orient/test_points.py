"""GCP / check-point files: CSV and GeoJSON, and every bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tiledsm.errors import InputFileError
from tiledsm.orient.points import read_points

IMAGES = ["/data/left.tif", "/data/right.tif"]
SHAPES = [(100, 200), (100, 200)]
HEADER = "id,image,lon,lat,h,row,col\n"


def _csv(tmp_path, body, header=HEADER):
    p = tmp_path / "gcps.csv"
    p.write_text(header + body)
    return p


def test_csv_two_images_one_point(tmp_path):
    p = _csv(tmp_path, "a,left.tif,5.1,44.2,300,10.5,20.25\na,right.tif,5.1,44.2,300,11,21\nb,right,5.2,44.3,310,0,200\n")
    g = read_points(p, IMAGES, SHAPES)
    assert g.ids.tolist() == ["a", "a", "b"] and g.image.tolist() == [0, 1, 1]
    assert g.point_ids == ["a", "b"]
    np.testing.assert_array_equal(g.row, [10.5, 11, 0])
    np.testing.assert_array_equal(g.count_per_image(2), [1, 2])


def test_csv_columns_in_any_order_extra_ignored(tmp_path):
    p = _csv(tmp_path, "10,20,a,left.tif,300,5.1,44.2,x\n", header="row,col,id,image,h,lon,lat,note\n")
    g = read_points(p, IMAGES)
    assert (g.row[0], g.col[0], g.lon[0], g.h[0]) == (10, 20, 5.1, 300)


def test_geojson_equals_csv(tmp_path):
    feats = [{"type": "Feature", "geometry": {"type": "Point", "coordinates": [5.1, 44.2, 300.0]},
              "properties": {"id": "a", "image": "left.tif", "row": 10.5, "col": 20.25}}]
    p = tmp_path / "g.geojson"
    p.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    g = read_points(p, IMAGES, SHAPES)
    c = read_points(_csv(tmp_path, "a,left.tif,5.1,44.2,300,10.5,20.25\n"), IMAGES, SHAPES)
    for k in ("lon", "lat", "h", "row", "col", "image"):
        np.testing.assert_array_equal(getattr(g, k), getattr(c, k))


@pytest.mark.parametrize("header,body,match", [
    ("id,image,lon,lat,height,row,col\n", "a,left.tif,5,44,3,1,1\n", r"lacks column\(s\) h; expected id,image,lon,lat,h,row,col"),
    ("id,img,x,y,h,row,col\n", "a,left.tif,5,44,3,1,1\n", r"lacks column\(s\) image, lon, lat"),
    (HEADER, "a,left.tif,5,44,3,1,1\na,left.tif,5,44,3,2,2\n", r"line 3: duplicate id 'a': measured twice in left.tif"),
    (HEADER, "a,left.tif,5,44,3,1,1\na,right.tif,5,44,9,2,2\n", r"line 3: duplicate id 'a' with other ground coordinates"),
    (HEADER, "a,left.tif,5,44,3,150,1\n", r"line 2: point 'a' at row 150, col 1 lies outside left.tif \(100 x 200"),
    (HEADER, "a,left.tif,5,44,3,-1,1\n", r"lies outside left.tif"),
    (HEADER, "a,other.tif,5,44,3,1,1\n", r"image 'other.tif', which is not one of left.tif, right.tif"),
    (HEADER, "a,left.tif,5,north,3,1,1\n", r"line 2: lat of point 'a' is not a number"),
    (HEADER, "", r"no points"),
])
def test_bad_csv(tmp_path, header, body, match):
    with pytest.raises(InputFileError, match=match):
        read_points(_csv(tmp_path, body, header), IMAGES, SHAPES)


def test_bad_geojson_and_missing_file(tmp_path):
    p = tmp_path / "g.geojson"
    p.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": [5, 44, 3]}, "properties": {"id": "a"}}]}))
    with pytest.raises(InputFileError, match="feature 0: properties lack image, row, col"):
        read_points(p, IMAGES)
    p.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": [5, 44]}, "properties": {}}]}))
    with pytest.raises(InputFileError, match=r"coordinates \[lon, lat, h\]"):
        read_points(p, IMAGES)
    with pytest.raises(InputFileError, match="no such points file"):
        read_points(tmp_path / "none.csv", IMAGES)
