"""``ruff check`` (its settings: ``[tool.ruff]`` in pyproject.toml) passes on the whole tree."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

def ruff_executable() -> str | None:
    """The ruff of this interpreter's environment (the [test] extra installs it), else one on PATH."""
    here = Path(sys.executable).parent
    return shutil.which("ruff", path=os.pathsep.join([str(here), os.environ.get("PATH", "")]))


def ruff_violations(*args: str) -> list[dict]:
    """``ruff check ARGS`` in the repository (no ARGS: the whole tree as configured) as JSON records."""
    exe = ruff_executable()
    if exe is None:
        pytest.skip("the ruff executable is not installed (pip install -e '.[test]' installs it)")
    proc = subprocess.run([exe, "check", "--no-cache", "--output-format", "json", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode in (0, 1), proc.stderr  # 1: violations found; anything else: ruff itself failed
    return json.loads(proc.stdout or "[]")


def _where(v: dict) -> str:
    return Path(v["filename"]).resolve().relative_to(ROOT).as_posix()


def _lines(found: list[dict]) -> str:
    return "\n".join(f"{_where(v)}:{v['location']['row']}: {v['code']} {v['message']}" for v in found)


def test_ruff_passes():
    found = ruff_violations()
    assert not found, "ruff check (run `ruff check --fix` for the fixable ones):\n" + _lines(found)


def test_ruff_catches_a_violation(tmp_path):
    """The same settings flag an unused import and unsorted imports in a file that has them."""
    bad = tmp_path / "probe.py"
    bad.write_text("import sys\nimport os\n\nprint(os.sep)\n")
    codes = {v["code"] for v in ruff_violations("--config", str(ROOT / "pyproject.toml"), str(bad))}
    assert {"F401", "I001"} <= codes
