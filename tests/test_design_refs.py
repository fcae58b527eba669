"""Every design reference resolves inside the repository: "docs/design.md §N.M" names a section there."""

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _tracked() -> list[Path]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True).stdout.split()
    files = [ROOT / f for f in out] or [p for p in ROOT.rglob("*") if ".venv" not in p.parts]
    return [f for f in files if f.suffix in (".py", ".md", ".ipynb", ".js", ".html", ".txt") and f.is_file()]


def test_design_sections_cited_exist():
    design = (ROOT / "docs" / "design.md").read_text(encoding="utf-8")
    sections = set(re.findall(r"^#{2,3} (\d+(?:\.\d+)?)[ .]", design, flags=re.M))
    assert {"2.1", "2.2", "2.3", "2.4", "2.5", "2.6"} <= sections
    cited = {}
    for f in _tracked():
        for sec in re.findall(r"docs/design\.md §(\d+(?:\.\d+)?)", f.read_text(encoding="utf-8", errors="replace")):
            cited.setdefault(sec, []).append(f.name)
        for sec in re.findall(r"(?<![\w/])§(\d+\.\d+)", f.read_text(encoding="utf-8", errors="replace")) if f.name == "design.md" else []:
            cited.setdefault(sec, []).append(f.name)
    assert cited, "no file cites docs/design.md"
    missing = {s: names[:3] for s, names in cited.items() if s not in sections}
    assert not missing, missing


def test_no_reference_leaves_the_repository():
    """The shared design note lives outside the repository: nothing points at it."""
    bad = []
    for f in _tracked():
        if f.name in ("test_design_refs.py",):
            continue
        text = f.read_text(encoding="utf-8", errors="replace")
        if "../shared/DESIGN" in text or re.search(r"\bDESIGN(\.md)? ?§?\d", text):
            bad.append(str(f.relative_to(ROOT)))
    assert not bad, bad
