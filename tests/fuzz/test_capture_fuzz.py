"""Robustness: malformed captures never crash, stall or leave half a material.

Each generated case writes a capture directory (tests/fuzz/captures.py: a valid tiny capture,
then up to three mutations of capture.json or its files) and runs ``torchmetal fit`` on it.
The property (tests/fuzz/harness.py): exit 0 with a complete, finite material, or exit 2 with
one line saying what was expected and what was found; never a traceback or a partial output.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from hypothesis import event, given, settings

from tests.fuzz.captures import Recipe, recipes, write_recipe
from tests.fuzz.harness import FUZZ, check_outcome, examples, fresh_output, run_fit, threads_one

threads_one()

N_CAPTURES = examples(300)


def _fit_recipe(r: Recipe, tally: str) -> str:
    with tempfile.TemporaryDirectory(prefix="tm-fuzz-") as tmp:
        cap = write_recipe(Path(tmp) / "cap", r)
        out = fresh_output(Path(tmp))
        o = run_fit(cap, out)
        kind = check_outcome(o, out, tally)
        if kind == "material":
            return kind
        where = o.stderr.split("error: ", 1)[-1].split(": ")[0].replace(str(cap), "CAPTURE")
        return "error: " + where[:60]


@settings(FUZZ, max_examples=N_CAPTURES)
@given(recipes())
def test_fit_on_fuzzed_capture_ends_with_material_or_one_line(r):
    event(_fit_recipe(r, "capture fuzz (mutations)"))


#: the valid corners every run of the suite covers, whatever the generator drew: 1–3 shots,
#: 1×1 and 2×3 images, all black, all saturated, an empty mask, float images at 0×0
CORNERS = [
    Recipe("plain", 1, "png8", "srgb", (20, 20), ()),
    Recipe("flakes", 3, "png16", "linear", (20, 20), ()),
    Recipe("plain", 2, "npy", "linear", (1, 1), ()),
    Recipe("flakes", 3, "png8", "linear", (2, 3), ()),
    Recipe("plain", 3, "npy", "linear", (0, 0), ()),
    Recipe("plain", 3, "png8", "srgb", (20, 20), (("all_images", "black"),)),
    Recipe("flakes", 3, "png16", "srgb", (20, 20), (("all_images", "saturated"),)),
    Recipe("flakes", 2, "npy", "linear", (20, 20), (("all_images", "saturated"),)),
    Recipe("plain", 3, "png8", "srgb", (20, 20), (("mask", "empty"),)),
    Recipe("plain", 3, "png8", "srgb", (20, 20), (("mask", "one_px"),)),
    Recipe("flakes", 3, "png8", "srgb", (20, 20), (("saturated", "all"),)),
    Recipe("flakes", 3, "npy", "linear", (20, 20), (("normals", "downward"),)),
    Recipe("flakes", 3, "npy", "linear", (20, 20), (("normals", "horizontal"),)),
    Recipe("plain", 3, "npy", "linear", (20, 20), (("all_images", "huge_npy"),)),
    Recipe("plain", 3, "npy", "linear", (20, 20), (("image", 0, "tiny_npy"),)),
    Recipe("plain", 3, "png8", "srgb", (20, 20), (("set", ("shots", 0, "light_intensity"), [0, 0, 0]),)),
    Recipe("plain", 3, "png8", "srgb", (20, 20), (("set", ("surface", "width"), 1e-300),)),
    Recipe("plain", 3, "png8", "srgb", (20, 20), (("set", ("surface", "width"), 1e308),)),
    Recipe("plain", 3, "png8", "srgb", (20, 20), (("set", ("shots", 1, "light", 2), 1e-300),)),
    Recipe("plain", 3, "png8", "srgb", (20, 20), (("set", ("shots", 1, "camera", 0), 1e30),)),
    Recipe("plain", 3, "png8", "srgb", (20, 20), (("set", ("shots", 0, "light", 0), 10 ** 400),)),
    Recipe("plain", 3, "png8", "srgb", (20, 20), (("set", ("surface", "height"), 10 ** 400),)),
    Recipe("plain", 3, "png8", "srgb", (20, 20), (("shots", "many_same"),)),
]


@pytest.mark.parametrize("r", CORNERS, ids=lambda r: f"{r.base}-{r.shots}-{r.encoding}-{r.size}-{r.mutations}"[:90])
def test_fit_on_corner_capture_ends_with_material_or_one_line(r):
    _fit_recipe(r, "capture corners (fixed)")


#: a few malformed captures through a real process: what a user's terminal shows
SUBPROCESS = [
    Recipe("plain", 2, "png8", "srgb", (20, 20), (("image", 1, "truncated"),)),
    Recipe("plain", 2, "npy", "linear", (20, 20), (("image", 0, "nan_npy"),)),
    Recipe("plain", 2, "png8", "srgb", (20, 20), (("set", ("shots", 0, "light", 0), 10 ** 400),)),
]


@pytest.mark.parametrize("r", SUBPROCESS, ids=["truncated-png", "nan-npy", "huge-int"])
def test_cli_process_prints_one_line(r, tmp_path):
    cap = write_recipe(tmp_path / "cap", r)
    out = fresh_output(tmp_path)
    proc = subprocess.run([sys.executable, "-m", "torchmetal", "fit", str(cap), "-o", str(out), "-q"],
                          capture_output=True, text=True, timeout=300, env={**__import__("os").environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "expected" in lines[0] and not out.exists()
