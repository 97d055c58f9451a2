"""Config validation, environment overrides and the console script, run as a user would."""
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from companion.config import DEFAULT_CONFIG_PATH, ConfigError, dump_config, load_config

TERRASLAM = [str(Path(sys.executable).with_name("terraslam"))]


def write(tmp_path, data) -> Path:
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_default_yaml_lists_every_key_and_validates():
    data = yaml.safe_load(DEFAULT_CONFIG_PATH.read_text())
    cfg = load_config(DEFAULT_CONFIG_PATH, environ={})
    dumped = cfg.model_dump(mode="json", by_alias=True)
    assert set(data) == set(dumped)
    for section, values in dumped.items():
        missing = set(values) - set(data[section])
        assert not missing, f"config/default.yaml section {section} lacks keys {sorted(missing)}"


def test_unknown_key_is_named(tmp_path):
    with pytest.raises(ConfigError) as e:
        load_config(write(tmp_path, {"mavlink": {"conect": "udpout:1.2.3.4:1"}}), environ={})
    assert "mavlink.conect" in str(e.value) and "unknown key" in str(e.value)


def test_wrong_type_names_key_value_and_expectation(tmp_path):
    with pytest.raises(ConfigError) as e:
        load_config(write(tmp_path, {"slam": {"n_features": "lots"}}), environ={})
    msg = str(e.value)
    assert "slam.n_features" in msg and "'lots'" in msg and "integer" in msg


def test_out_of_range_value(tmp_path):
    with pytest.raises(ConfigError) as e:
        load_config(write(tmp_path, {"mavlink": {"gps_id": 3}}), environ={})
    assert "mavlink.gps_id" in str(e.value) and "less than or equal to 1" in str(e.value)


def test_bad_yaml_and_missing_file(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("camera: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(p, environ={})
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml", environ={})


def test_env_overrides(tmp_path):
    cfg = load_config(write(tmp_path, {}), environ={"TERRASLAM_MAVLINK__CONNECT": "/dev/ttyTHS1", "TERRASLAM_SLAM__N_FEATURES": "1200", "HOME": "/x"})
    assert cfg.mavlink.connect == "/dev/ttyTHS1"
    assert cfg.slam.n_features == 1200
    with pytest.raises(ConfigError, match="environment"):
        load_config(write(tmp_path, {}), environ={"TERRASLAM_MAVLINK__RATE_HZ": "1000"})


def test_dump_round_trips(tmp_path):
    cfg = load_config(environ={})
    p = tmp_path / "dumped.yaml"
    p.write_text(dump_config(cfg))
    assert load_config(p, environ={}) == cfg


def run_cli(*args, env=None):
    return subprocess.run(TERRASLAM + list(args), capture_output=True, text=True, timeout=120, env={**os.environ, **(env or {})})


def test_cli_help_version_and_dump(tmp_path):
    r = run_cli("--help")
    assert r.returncode == 0
    for cmd in ("demo", "run", "replay", "sim", "gis", "align-offline", "bench", "config"):
        assert cmd in r.stdout
    r = run_cli("--version")
    assert r.returncode == 0 and r.stdout.startswith("terraslam ")
    r = run_cli("config", "dump", env={"TERRASLAM_MAVLINK__AUTOPILOT": "px4"})
    assert r.returncode == 0
    assert yaml.safe_load(r.stdout)["mavlink"]["autopilot"] == "px4"


def test_cli_bad_config_exits_nonzero_with_message(tmp_path):
    r = run_cli("config", "dump", "--config", str(write(tmp_path, {"camera": {"fps": -5}})))
    assert r.returncode == 2
    assert "camera.fps" in r.stderr and "-5" in r.stderr


def test_frame_period_longer_than_fix_age_is_refused(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("camera:\n  fps: 1.0\n")
    with pytest.raises(ConfigError, match=r"camera.fps 1 .* mavlink.max_fix_age_s 0.5"):
        load_config(p, environ={})
    p.write_text("camera:\n  fps: 1.0\nmavlink:\n  max_fix_age_s: 1.5\n")
    assert load_config(p, environ={}).camera.fps == 1.0
