"""Print the README's set-up and test commands, so CI runs exactly what the README tells a newcomer.

    python3 scripts/readme_commands.py 1    # the first ```bash block under "## Set up and run"
    python3 scripts/readme_commands.py 2    # the second

.ci/run runs both; tests/test_readme_ci.py checks the README keeps two one-line commands there.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"
SECTION = "## Set up and run"


def readme_commands(text: str | None = None) -> list[str]:
    """The ```bash blocks of the README's set-up section, each one command line, in order."""
    text = README.read_text(encoding="utf-8") if text is None else text
    if SECTION not in text:
        raise ValueError(f"README.md: expected a section {SECTION!r}, found none")
    body = text.split(SECTION, 1)[1]
    body = re.split(r"^## ", body, maxsplit=1, flags=re.M)[0]
    blocks = re.findall(r"^```bash\n(.*?)^```", body, flags=re.M | re.S)
    cmds = []
    for b in blocks:
        lines = [ln for ln in b.strip().splitlines() if ln.strip()]
        if len(lines) != 1:
            raise ValueError(f"README.md: expected one command line per bash block, found {len(lines)}: {b!r}")
        cmds.append(lines[0].strip())
    return cmds


def main(argv: list[str]) -> int:
    cmds = readme_commands()
    if len(cmds) != 2 or len(argv) != 1 or argv[0] not in ("1", "2"):
        print(f"readme_commands: expected argument 1 or 2 and two commands in README.md, found {argv} and {len(cmds)}",
              file=sys.stderr)
        return 2
    print(cmds[int(argv[0]) - 1])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
