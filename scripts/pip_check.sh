#!/usr/bin/env bash
# The plain-pip job: what `pip install torchmetal` gives a user, outside the checkout, step by step.
#
#   bash scripts/pip_check.sh [WORKDIR]        (run from anywhere; WORKDIR default: a new temp folder)
#
# A second venv gets torch==2.13.0 (the CPU build) and then a plain `pip install .` (no extras: the
# wheel's build hook copies onnxruntime-web from node_modules, so `npm ci` must have run). From a folder
# outside the repository: synth → fit → every export format → `view --no-open` answering HTTP on
# 127.0.0.1; then `pip install ".[photos]"` → board → generated phone photos → capture.
# One line per step, "ok" or "FAILED" (with the end of its log); exits 1 when any step failed.
set -uo pipefail
REPO="$(cd "$(dirname "$0")/.." && pwd)"
WORK="${1:-$(mktemp -d "${TMPDIR:-/tmp}/torchmetal-pip-check.XXXXXX")}"
mkdir -p "$WORK" && cd "$WORK" || exit 1
PY="${PYTHON:-python3}"
V="$WORK/venv"
LOG="$WORK/logs"
mkdir -p "$LOG"
FAILED=0
N=0
T0=$SECONDS

step() {  # step NAME COMMAND...: run it, log its output, print one line
    local name="$1" t=$SECONDS log
    shift
    N=$((N + 1))
    log="$LOG/$(printf '%02d' "$N")-${name//[^A-Za-z0-9_.-]/_}.log"
    if "$@" >"$log" 2>&1; then
        printf 'ok      %-34s %4ds\n' "$name" $((SECONDS - t))
    else
        printf 'FAILED  %-34s %4ds  (%s)\n' "$name" $((SECONDS - t)) "$log"
        tail -n 15 "$log" | sed 's/^/        | /'
        FAILED=1
    fi
}

view_answers() {  # torchmetal view --no-open answers HTTP on 127.0.0.1, then stops
    local port pid ok=1
    port=$("$V/bin/python" -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
    "$V/bin/torchmetal" view mat --port "$port" --no-open &
    pid=$!
    for _ in $(seq 1 120); do
        if curl -fsS "http://127.0.0.1:$port/" -o view-index.html 2>/dev/null; then ok=0; break; fi
        kill -0 "$pid" 2>/dev/null || break
        sleep 0.5
    done
    [ "$ok" -eq 0 ] && curl -fsS "http://127.0.0.1:$port/config.json" -o view-config.json && grep -qi "<html" view-index.html || ok=1
    kill "$pid" 2>/dev/null
    wait "$pid" 2>/dev/null
    return "$ok"
}

site_has_ort() {  # the web site is self-contained: onnxruntime-web copied from the wheel, not the checkout
    ls site/ort/ort.wasm.min.mjs site/ort/ort-wasm-simd-threaded.wasm site/index.html site/config.json &&
        "$V/bin/python" -c 'import torchmetal, pathlib; p = pathlib.Path(torchmetal.__file__).parent / "_npm/onnxruntime-web/dist"; assert p.is_dir(), p; print(p)'
}

flake_material() {  # the synthetic truth with a flake model: the exporters' flake path (flake2d, baked glints)
    "$V/bin/python" -c 'from torchmetal.flakes.model import FlakeModel; from torchmetal.material import save_material
from torchmetal.synth import synth_capture
m = synth_capture(size=64, shots=1, seed=0, texture="procedural", flakes=FlakeModel(density=0.003, seed=0)).material()
assert m.flakes is not None
save_material(m, "mat-flakes")'
}

no_scipy() {  # nothing of a plain install needs scipy (only the [bench] extra does)
    ! "$V/bin/python" -c 'import scipy' 2>/dev/null
}

echo "plain-pip job: $REPO -> $WORK"
step "venv"                     "$PY" -m venv "$V"
step "pip install torch==2.13.0" "$V/bin/pip" install -q torch==2.13.0
step "pip install . (no extras)" "$V/bin/pip" install -q "$REPO"
rm -rf "$REPO/build"  # setuptools' in-tree build folder
step "torchmetal --help"        "$V/bin/torchmetal" --help
step "no scipy installed"       no_scipy
step "synth"                    "$V/bin/torchmetal" synth -o cap --flakes --size 96 --shots 8
step "fit"                      "$V/bin/torchmetal" fit cap -o mat -q
step "plan"                     "$V/bin/torchmetal" plan cap -n 2 -o plan
step "export onnx"              "$V/bin/torchmetal" export mat -o renderer.onnx
step "export gltf"              "$V/bin/torchmetal" export mat --format gltf -o gltf/material.gltf
step "export glb"               "$V/bin/torchmetal" export mat --format glb -o material.glb
step "export mtlx"              "$V/bin/torchmetal" export mat --format mtlx -o mtlx/material.mtlx
step "export usd"               "$V/bin/torchmetal" export mat --format usd -o usd/material.usda
step "export web"               "$V/bin/torchmetal" export mat --format web -o site
step "web site self-contained"  site_has_ort
step "material with flakes"     flake_material
step "export gltf, flakes"      "$V/bin/torchmetal" export mat-flakes --format gltf -o flakes-gltf/material.gltf
step "export mtlx, flakes"      "$V/bin/torchmetal" export mat-flakes --format mtlx -o flakes-mtlx/material.mtlx
step "export usd, flakes"       "$V/bin/torchmetal" export mat-flakes --format usd -o flakes-usd/material.usda
step "view --no-open (HTTP)"    view_answers
step "pip install .[photos]"    "$V/bin/pip" install -q "$REPO[photos]"
rm -rf "$REPO/build"
step "board"                    "$V/bin/torchmetal" board -o board
step "simulated phone photos"   "$V/bin/python" "$REPO/scripts/simulate_photos.py" board/board.json -o photos
step "capture"                  "$V/bin/torchmetal" capture photos/IMG_00*.jpg --board board/board.json -o photo-cap --flash-offset 12 -4 0 --resolution 128 -q
echo "plain-pip job: $N steps, $((SECONDS - T0)) s, $([ $FAILED -eq 0 ] && echo 'all ok' || echo 'FAILED')"
exit $FAILED
