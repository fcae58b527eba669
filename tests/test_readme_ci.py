"""The README's two set-up commands are what CI runs, and the set-up script does what the README says."""

import importlib.util
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _readme_commands():
    spec = importlib.util.spec_from_file_location("readme_commands", ROOT / "scripts" / "readme_commands.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_has_two_one_line_commands():
    cmds = _readme_commands().readme_commands()
    assert cmds == ["bash scripts/setup.sh", ". .venv/bin/activate && python -m pytest -q -n 2 --dist loadfile"]


def test_ci_runs_exactly_the_readme_commands():
    """.ci/run takes both commands from README.md (nothing of its own installs or tests), then the plain-pip job."""
    run = (ROOT / ".ci" / "run").read_text()
    body = [ln.strip() for ln in run.splitlines() if ln.strip() and not ln.strip().startswith("#")]
    assert body == [
        "set -euo pipefail", 'cd "$(dirname "$0")/.."', "for n in 1 2; do",
        'cmd="$(python3 scripts/readme_commands.py "$n")"', 'echo "+ $cmd"', 'bash -c "$cmd"', "done",
        "bash scripts/pip_check.sh",
    ]
    for n, cmd in enumerate(_readme_commands().readme_commands(), 1):
        out = subprocess.run([sys.executable, str(ROOT / "scripts" / "readme_commands.py"), str(n)],
                             capture_output=True, text=True, check=True).stdout
        assert out.strip() == cmd


def test_readme_commands_rejects_a_multi_line_block():
    mod = _readme_commands()
    text = "## Set up and run\n\n```bash\npip install x\ntorchmetal demo\n```\n"
    try:
        mod.readme_commands(text)
    except ValueError as e:
        assert "one command line" in str(e)
    else:
        raise AssertionError("a two-line block was accepted")


def test_setup_script_installs_what_the_tests_need():
    sh = (ROOT / "scripts" / "setup.sh").read_text()
    assert sh.index("pip install -q torch==2.13.0") < sh.index('pip install -q -e ".[test]"')  # the CPU build first
    for needed in ("npm ci", "apt-get install", "chromium", "sudo", "torchmetal demo"):
        assert needed in sh, needed
    assert subprocess.run(["bash", "-n", str(ROOT / "scripts" / "setup.sh")]).returncode == 0
    assert subprocess.run(["bash", "-n", str(ROOT / "scripts" / "pip_check.sh")]).returncode == 0
