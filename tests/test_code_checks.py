"""The code's own rules, checked on the whole tree with every `make test`: the import layers of
CONTRIBUTING.md as import-linter contracts (pyproject.toml [tool.importlinter], on the real import
graph) and ruff's lint and import order (pyproject.toml [tool.ruff])."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _run(tool: str, *args: str) -> subprocess.CompletedProcess:
    """A console script of this interpreter's environment (the `test` extra installs both), run in
    the repository root so that it checks this tree."""
    exe = Path(sys.executable).with_name(tool)
    assert exe.exists(), f"{exe} missing: pip install -e '.[test]'"
    return subprocess.run([str(exe), *args], cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_the_packages_import_only_what_their_layer_allows():
    r = _run("lint-imports", "--no-cache")
    assert r.returncode == 0, r.stdout + r.stderr
    assert "0 broken" in r.stdout


def test_ruff_finds_nothing():
    r = _run("ruff", "check", "--no-cache", "--output-format", "concise", ".")
    assert r.returncode == 0, r.stdout + r.stderr
