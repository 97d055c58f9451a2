"""The systemd unit, checked by systemd's own tools (systemd-analyze verify / security --offline).

No systemd runs as PID 1 in CI containers, so the unit is not started here; the notify/watchdog
protocol it relies on is tested against a real socket in test_companion_supervisor.py.
"""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parent.parent / "systemd" / "terraslam.service"
SYSUSERS = UNIT.with_name("terraslam.sysusers.conf")

pytestmark = pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")


def _local_copy(tmp_path: Path, text: str | None = None) -> Path:
    """The unit with ExecStart pointed at this checkout's entry point (verify checks it exists)."""
    exe = Path(sys.executable).with_name("terraslam")
    if not exe.exists():
        pytest.skip("terraslam entry point not installed in this environment")
    unit = tmp_path / "terraslam.service"
    unit.write_text((text or UNIT.read_text()).replace("/opt/terraslam/.venv/bin/terraslam", str(exe)))
    return unit


def _verify(unit: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, timeout=60)


def test_unit_verifies_without_warnings(tmp_path: Path) -> None:
    result = _verify(_local_copy(tmp_path))
    assert result.returncode == 0 and result.stderr.strip() == "", result.stderr


def test_verify_would_catch_a_misspelt_key(tmp_path: Path) -> None:
    broken = UNIT.read_text().replace("WatchdogSec=", "WatchdogSecs=")
    result = _verify(_local_copy(tmp_path, broken))
    assert "Unknown key" in result.stderr and "WatchdogSecs" in result.stderr


def test_unit_is_notify_watchdog_restart_and_hardened(tmp_path: Path) -> None:
    result = subprocess.run(
        ["systemd-analyze", "security", "--offline=yes", str(_local_copy(tmp_path))], capture_output=True, text=True, timeout=60
    )
    m = re.search(r"Overall exposure level for terraslam.service: ([0-9.]+)", result.stdout)
    assert m, result.stdout + result.stderr
    exposure = float(m.group(1))
    print(f"systemd-analyze security exposure: {exposure}")
    assert exposure <= 2.5  # systemd's scale: 0 (locked down) … 10 (unprotected); ≤ 2.5 is its best band ("OK")
    # the directives the service contract depends on (the supervisor sends READY/WATCHDOG/STOPPING)
    keys = dict(line.split("=", 1) for line in UNIT.read_text().splitlines() if "=" in line and not line.startswith("#"))
    assert keys["Type"] == "notify" and keys["Restart"] == "on-failure" and keys["User"] == "terraslam"
    assert keys["ProtectSystem"] == "strict" and keys["DevicePolicy"] == "closed"


def test_sysusers_snippet_parses(tmp_path: Path) -> None:
    if shutil.which("systemd-sysusers") is None:
        pytest.skip("systemd-sysusers not installed")
    # --root on an empty tree: sysusers creates the user there, never touching the host's /etc
    (tmp_path / "etc").mkdir()
    result = subprocess.run(["systemd-sysusers", f"--root={tmp_path}", str(SYSUSERS)], capture_output=True, text=True, timeout=60)
    passwd = (tmp_path / "etc" / "passwd").read_text() if (tmp_path / "etc" / "passwd").exists() else ""
    assert result.returncode == 0, result.stderr
    assert re.search(r"^terraslam:x:\d+:\d+:TerraSLAM companion:/var/lib/terraslam:/usr/sbin/nologin$", passwd, re.M)
