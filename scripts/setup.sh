#!/usr/bin/env bash
# Set-up on a fresh machine (Debian, Python 3.11), from anywhere in the repository; the README's first command.
#
#   1. Debian's chromium for the browser tests (apt-get, with sudo when not root), unless it is there;
#      Node.js + npm the same way when npm is missing. When apt cannot be used, one line says so.
#   2. The JavaScript dependencies from the lock file: `npm ci` (onnxruntime-web, gltf-validator, three).
#   3. The venv .venv: torch==2.13.0 first (pip takes the CPU build from local disk), then torchmetal
#      editable with the test extra (all extras the tests use).
#   4. `torchmetal demo`.
# Re-running it is safe: it reuses .venv and what apt already installed.
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
say() { printf 'setup: %s\n' "$*"; }

# 1. system packages --------------------------------------------------------------------------------
want=()
command -v chromium >/dev/null 2>&1 || want+=(chromium)
command -v npm >/dev/null 2>&1 || want+=(nodejs npm)
if [ ${#want[@]} -gt 0 ]; then
    SUDO=()
    if [ "$(id -u)" -ne 0 ]; then
        if command -v sudo >/dev/null 2>&1; then SUDO=(sudo); else SUDO=(none); fi
    fi
    if [ "${SUDO[0]:-}" != none ] && command -v apt-get >/dev/null 2>&1 &&
        "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null &&
        "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${want[@]}" >/dev/null; then
        say "installed Debian's ${want[*]}"
    else
        say "could not install Debian's ${want[*]} (needs apt-get and root or sudo): without chromium the browser tests skip, without npm the glTF-validator and web tests fail"
    fi
fi

# 2. JavaScript dependencies ----------------------------------------------------------------------------
if command -v npm >/dev/null 2>&1; then
    npm ci --no-audit --no-fund --loglevel=error >/dev/null
    say "npm ci: node_modules from package-lock.json"
fi

# 3. Python -------------------------------------------------------------------------------------------
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q torch==2.13.0
.venv/bin/python -m pip install -q -e ".[test]"
say "venv .venv: torch $(.venv/bin/python -c 'import torch; print(torch.__version__)'), torchmetal[test] (editable)"

# 4. the demo -----------------------------------------------------------------------------------------
.venv/bin/torchmetal demo
