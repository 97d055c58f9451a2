"""`terraslam sim generate` for every required scenario, and the dataset reader's error messages."""
from __future__ import annotations

import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from companion.cli import _register_subcommands, app
from companion.dataset import DatasetError, read_dataset
from mavlink_bridge.types import GpsFixType

REQUIRED = ("nominal", "stale", "dark", "bright", "fast", "loop", "survey")


@pytest.fixture(scope="module")
def runner():
    _register_subcommands()
    return CliRunner()


@pytest.mark.parametrize("name", REQUIRED)
def test_generate_each_named_scenario(runner, tmp_path, name):
    out = tmp_path / name
    r = runner.invoke(app, ["sim", "generate", "--scenario", name, "--out", str(out), "--frames", "3", "--seed", "4"])
    assert r.exit_code == 0, r.output
    ds = read_dataset(out)
    assert ds.name == name and ds.n_frames == 3 and ds.fps == 30.0
    assert len(ds.truth) == 3 and ds.gnss and ds.attitude
    assert [p.name for p in ds.gis_files] == ["model.ply", "model.laz", "buildings.geojson"]
    steps = list(ds.steps())
    assert [s.frame.seq for s in steps] == [0, 1, 2] and steps[0].frame.image.shape == (480, 640, 3)
    # the rough initial position is within its stated σ-scale of the truth
    p0 = ds.origin.geodetic_to_enu(ds.rough_position.lat_deg, ds.rough_position.lon_deg, ds.rough_position.h_ellipsoid_m)
    assert np.linalg.norm(p0 - ds.truth[0].T_enu_body[:3, 3]) < 4 * ds.rough_position.sigma_m


def test_generate_with_gnss_timeline_and_errors(runner, tmp_path):
    out = tmp_path / "ds"
    r = runner.invoke(app, ["sim", "generate", "-s", "nominal", "-o", str(out), "-n", "15", "--gnss", "dropout@0.2"])
    assert r.exit_code == 0, r.output
    ds = read_dataset(out)
    assert ds.gnss[0].fix_type == GpsFixType.FIX_3D and ds.gnss[-1].fix_type == GpsFixType.NO_FIX
    r = runner.invoke(app, ["sim", "generate", "-s", "nominal", "-o", str(out), "-n", "2"])
    assert r.exit_code != 0 and "not empty" in r.output
    r = runner.invoke(app, ["sim", "generate", "-s", "moon", "-o", str(tmp_path / "x")])
    assert r.exit_code != 0 and "unknown scenario 'moon'" in r.output
    r = runner.invoke(app, ["sim", "generate", "-s", "nominal", "-o", str(tmp_path / "y"), "--gnss", "dropout"])
    assert r.exit_code != 0 and "bad GNSS timeline item" in r.output
    r = runner.invoke(app, ["sim", "generate", "-s", "nominal", "-o", str(tmp_path / "z"), "-n", "999999"])
    assert r.exit_code != 0 and "n_frames must be in" in r.output


def test_generate_at_another_frame_rate(runner, tmp_path):
    out = tmp_path / "ten"
    r = runner.invoke(app, ["sim", "generate", "-s", "nominal", "-o", str(out), "-n", "4", "--fps", "10"])
    assert r.exit_code == 0, r.output
    ds = read_dataset(out)
    assert ds.fps == 10.0 and np.allclose(np.diff(ds.frame_t_s), 0.1)
    r = runner.invoke(app, ["sim", "generate", "-s", "nominal", "-o", str(tmp_path / "fast"), "-n", "2", "--fps", "0.5"])
    assert r.exit_code != 0


def test_generate_stale_preset_and_registration_error(runner, tmp_path):
    import yaml

    out = tmp_path / "fa"
    r = runner.invoke(app, ["sim", "generate", "-s", "nominal", "-o", str(out), "-n", "2", "--stale", "F-A",
                            "--registration-error-m", "0.35"])
    assert r.exit_code == 0, r.output
    st = yaml.safe_load((out / "gis" / "stale_truth.yaml").read_text())
    assert np.hypot(*np.asarray(st["T_model_world_enu"])[:2, 3]) == pytest.approx(0.35)
    assert st["changed_building_ids"] and st["spec"]["registration_error_m"] == 0.35
    r = runner.invoke(app, ["sim", "generate", "-s", "nominal", "-o", str(tmp_path / "q"), "--stale", "F-Z"])
    assert r.exit_code != 0 and "unknown preset 'F-Z'" in r.output


def test_reader_names_the_broken_file(runner, tmp_path):
    src = tmp_path / "ok"
    assert runner.invoke(app, ["sim", "generate", "-s", "nominal", "-o", str(src), "-n", "2"]).exit_code == 0

    def broken(name, edit):
        d = tmp_path / name
        shutil.copytree(src, d)
        edit(d)
        with pytest.raises(DatasetError) as e:
            read_dataset(d)
        return str(e.value)

    assert "camera.yaml" in broken("nocam", lambda d: (d / "camera.yaml").unlink())
    assert "T_body_cam" in broken("mount", lambda d: (d / "mount.yaml").write_text("T_body_cam: [[1, 2], [3, 4]]\n"))
    for bad in ("[0.1, 0.2]", "[0.0, 0.0, .nan]", "[0, 0, -40]", "tall"):
        assert "p_body_gnss_m" in broken(f"antenna{bad}", lambda d, bad=bad: (d / "mount.yaml").write_text(
            (d / "mount.yaml").read_text().replace("p_body_gnss_m:", "p_body_gnss_m: " + bad + "\nx_old:")))
    assert read_dataset(src).p_body_gnss_m.tolist() == [0.0, 0.0, 0.0]
    assert "truth.csv" in broken("truth", lambda d: (d / "truth.csv").write_text(
        (d / "truth.csv").read_text().splitlines()[0] + "\n"))
    assert "gnss.csv:2" in broken("gnss", lambda d: (d / "gnss.csv").write_text(
        (d / "gnss.csv").read_text().replace("\n0.000000,3,", "\nabc,3,", 1)))
    assert "000001.png" in broken("img", lambda d: (d / "images" / "000001.png").unlink())
    assert "rough_position" in broken("site", lambda d: (d / "site.yaml").write_text("origin: {lat_deg: 1, lon_deg: 2, h_ellipsoid_m: 0}\n"))
    with pytest.raises(DatasetError, match="not found"):
        read_dataset(tmp_path / "nothing")
