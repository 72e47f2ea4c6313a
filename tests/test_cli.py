"""Command line: help for every command, `info` facts, errors named."""

import json
import subprocess
import sys

import numpy as np
import pytest
import rasterio
from pyproj import Geod
from rasterio.transform import RPCTransformer

from tiledsm.cli import build_parser, main
from tiledsm.cli.info import describe


def _commands():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sorted(sub.choices)


@pytest.mark.parametrize("command", _commands())
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as e:
        main([command, "--help"])
    assert e.value.code == 0
    assert "usage: tiledsm " + command in capsys.readouterr().out


def test_console_script_entry_point():
    out = subprocess.run([sys.executable, "-m", "tiledsm", "--help"], capture_output=True, text=True, check=True)
    assert "info" in out.stdout and "run" in out.stdout


def test_leave_runs_the_exit_handlers_and_flushes_before_ending(tmp_path):
    """``leave`` skips the interpreter's teardown, not what an exit owes:
    the exit handlers run, buffered output (a pipe is block-buffered)
    arrives, and the code is the process's."""
    child = (
        "import atexit; from tiledsm.cli import leave; "
        "atexit.register(lambda: print('handler ran')); "
        "print('buffered line'); leave(3)"
    )
    out = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True)
    assert out.returncode == 3
    assert out.stdout.splitlines() == ["buffered line", "handler ran"]


def test_info_s2p_image_matches_gdal(shared_data):
    path = shared_data("s2p_pair", "input_pair", "img_01.tif")
    info = describe(path)
    assert (info["width"], info["height"], info["dtype"]) == (1024, 1024, "uint16")
    assert "tags" in info["camera_source"].lower() or "gdal" in info["camera_source"].lower()
    with rasterio.open(path) as ds, RPCTransformer(ds.rpcs) as tr:
        h = ds.rpcs.height_off
        lon, lat = tr.xy([0, 1024], [0, 1024], zs=[h, h], offset="ul")
    np.testing.assert_allclose(info["footprint_lonlat"][0], [lon[0], lat[0]], atol=1e-7)
    np.testing.assert_allclose(info["footprint_lonlat"][2], [lon[1], lat[1]], atol=1e-7)
    # GSD from GDAL's localisation of neighbouring pixels at the centre
    with rasterio.open(path) as ds, RPCTransformer(ds.rpcs) as tr:
        lo, la = tr.xy([512, 513], [512, 512], zs=[h, h], offset="ul")
    gsd_row = Geod(ellps="WGS84").inv(lo[0], la[0], lo[1], la[1])[2]
    assert info["gsd_m"]["row"] == pytest.approx(gsd_row, rel=1e-4)
    assert 0.4 < info["gsd_m"]["col"] < 0.6  # Pleiades: ~0.5 m


def test_info_dsm_product(shared_data, capsys):
    path = shared_data("s2p_pair", "expected_output", "pair", "dsm.tif")
    assert main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["crs"] == "EPSG:32740" and info["resolution"] == [0.5, 0.5]
    assert 0.85 < info["valid_fraction"] < 0.95  # README: 11 % NaN
    assert 2260 < info["value_range"][0] < info["value_range"][1] < 2390


def test_info_errors_name_the_file(tmp_path, capsys):
    missing = tmp_path / "nope.tif"
    assert main(["info", str(missing)]) == 2
    assert str(missing) in capsys.readouterr().err
    garbage = tmp_path / "garbage.tif"
    garbage.write_bytes(b"not a tiff at all")
    assert main(["info", str(garbage)]) == 2
    err = capsys.readouterr().err
    assert str(garbage) in err and "readable" in err


def test_info_image_without_camera(tmp_path):
    path = tmp_path / "plain.tif"
    with rasterio.open(path, "w", driver="GTiff", width=8, height=8, count=1, dtype="uint8") as ds:
        ds.write(np.zeros((1, 8, 8), np.uint8))
    info = describe(path)
    assert info["camera"] is None and str(path) in info["camera_error"]


@pytest.mark.parametrize("command", ["dsm", "run", "sr", "compare"])
def test_planned_commands_offer_a_dry_run(command):
    """Issue 18: every computing command can be checked before it runs."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    text = sub.choices[command].format_help()
    assert "--dry-run" in text and "--workers" in text
    assert ("--allow-large" in text) == (command in ("dsm", "run"))


def test_debug_shows_the_traceback_behind_the_one_line_error(tmp_path):
    """An error is one line; ``tiledsm --debug`` adds the traceback above it."""
    import subprocess
    import sys

    missing = str(tmp_path / "nope.tif")
    plain = subprocess.run([sys.executable, "-m", "tiledsm", "info", missing], capture_output=True, text=True)
    debug = subprocess.run([sys.executable, "-m", "tiledsm", "--debug", "info", missing], capture_output=True, text=True)
    line = f"tiledsm info: error: {missing}: no such file"
    assert plain.returncode == debug.returncode == 2
    assert plain.stderr.strip() == line
    assert "Traceback (most recent call last)" in debug.stderr and "InputFileError" in debug.stderr
    assert debug.stderr.strip().splitlines()[-1] == line
