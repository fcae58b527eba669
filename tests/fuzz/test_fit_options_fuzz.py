"""Robustness: every fit option set ends with a complete material or a one-line error.

Small valid captures (zoo scenes shrunk to 24–48 px and 1–6 shots, or ``synth_capture`` with
random flakes / bumps / noise / layout) × option sets drawn from the fit's choices. Same
property as the capture fuzz (tests/fuzz/harness.py).
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

from hypothesis import event, given, settings
from hypothesis import strategies as st

from tests.fuzz.harness import FUZZ, check_outcome, examples, fresh_output, run_fit, threads_one

threads_one()

N_FITS = examples(60)

#: the fit's options (combined freely; --flakes on/off exclusive)
OPTIONS = {
    "normals-estimate": ["--normals", "estimate"],
    "lobe-auto": ["--lobe", "auto"],
    "specular-maps": ["--specular", "maps"],
    "flakes-on": ["--flakes", "on"],
    "flakes-off": ["--flakes", "off"],
    "robust-huber": ["--robust", "huber"],
    "scheme-paper": ["--scheme", "paper"],
}


@st.composite
def option_sets(draw) -> tuple[str, ...]:
    names = draw(st.lists(st.sampled_from(sorted(OPTIONS)), max_size=3, unique=True))
    if "flakes-on" in names and "flakes-off" in names:
        names.remove(draw(st.sampled_from(["flakes-on", "flakes-off"])))
    return tuple(sorted(names))  # () = the default


@st.composite
def sources(draw) -> tuple:
    """("zoo", scene name, size, shots) or ("synth", size, shots, seed, flakes, bumpy, noise, bits, layout)."""
    size = draw(st.integers(24, 48))
    shots = draw(st.integers(1, 6))
    if draw(st.integers(0, 3)):
        from torchmetal.synth.zoo import SCENES

        return ("zoo", draw(st.sampled_from(sorted(SCENES))), size, shots)
    return ("synth", size, shots, draw(st.integers(0, 2 ** 16)), draw(st.booleans()), draw(st.booleans()),
            draw(st.sampled_from([0.0, 0.01, 0.05])), draw(st.sampled_from([8, 16])),
            draw(st.sampled_from(["ring", "hemisphere", "grazing", "near", "far"])))


def write_source(src: tuple, root: Path) -> Path:
    with warnings.catch_warnings():  # the generators' own numpy warnings (e.g. a zoo scene too small for its
        warnings.simplefilter("ignore", RuntimeWarning)  # flake patch) are not the fit's: the fit's are checked
        return _write_source(src, root)


def _write_source(src: tuple, root: Path) -> Path:
    if src[0] == "zoo":
        from torchmetal.synth.zoo import SCENES, make_case

        _, name, size, shots = src
        return make_case(SCENES[name].with_(size=size, shots=shots, held=1), root).capture_dir
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.synth import synth_capture, write_synth

    _, size, shots, seed, flakes, bumpy, noise, bits, layout = src
    result = synth_capture(size=size, shots=shots, seed=seed, noise=noise, bits=bits, layout=layout, bumpy=bumpy,
                           flakes=FlakeModel(density=0.01, seed=seed) if flakes else None)
    write_synth(result, root)
    return root


def fit_case(src: tuple, names: tuple[str, ...], tally: str) -> str:
    with tempfile.TemporaryDirectory(prefix="tm-fuzz-fit-") as tmp:
        cap = write_source(src, Path(tmp) / "cap")
        out = fresh_output(Path(tmp))
        o = run_fit(cap, out, [a for n in names for a in OPTIONS[n]])
        return check_outcome(o, out, tally)


@settings(FUZZ, max_examples=N_FITS)
@given(sources(), option_sets())
def test_fit_options_end_with_material_or_one_line(src, names):
    kind = fit_case(src, names, "fit options (zoo + synth)")
    event(f"{kind}: {src[0]}")
    event("options: " + (" ".join(names) or "default"))
