"""What every fuzzed ``torchmetal fit`` must end with, and a tally of how the cases ended.

The property (robustness of ``torchmetal fit``): a run ends either with exit 0 and a complete material directory
(``material.json`` loads with :func:`torchmetal.material.load_material`, every array in it is
readable with numpy and finite), or with exit 2 and exactly one line on stderr that says what
was expected and what was found. Never an exception escaping :func:`torchmetal.cli.main` (a
traceback), never a non-finite value in the material, never a partial or temporary directory
left beside the output, never a stall.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import time
import traceback
import warnings
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, settings

from torchmetal.cli import main

#: hypothesis settings for the fuzz suite: reproducible (derandomized, no example database), no
#: per-example deadline (a fit's first call pays for lazy imports), the example count set per test.
FUZZ = settings(deadline=None, derandomize=True, database=None, print_blob=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])

#: scale the example counts for a deeper local search: TORCHMETAL_FUZZ_SCALE=10 python -m pytest tests/fuzz
SCALE = float(os.environ.get("TORCHMETAL_FUZZ_SCALE", "1"))


def examples(n: int) -> int:
    return max(1, round(n * SCALE))


#: one fuzzed fit may take this long before it counts as a stall (the cases are tiny: < 2 s)
STALL_S = 60.0

#: property name → Counter of outcomes ("material", "error: <first words>", ...); printed in the
#: terminal summary by tests/fuzz/conftest.py
TALLY: dict[str, Counter] = defaultdict(Counter)
TIMES: dict[str, list[float]] = defaultdict(list)


@dataclass
class Outcome:
    code: int | None
    stdout: str
    stderr: str
    seconds: float
    escaped: BaseException | None = None  # an exception that left main(): a traceback for the user
    trace: str = ""
    extra: dict = field(default_factory=dict)


def run_fit(capture: Path, output: Path, options: list[str] = ()) -> Outcome:
    """``torchmetal fit CAPTURE -o OUTPUT -q OPTIONS`` in process; stdout/stderr captured."""
    out, err = io.StringIO(), io.StringIO()
    t = time.perf_counter()
    code, escaped, trace = None, None, ""
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")  # what a user's terminal shows: each warning once per place
        try:
            code = main(["fit", str(capture), "-o", str(output), "-q", *options])
        except KeyboardInterrupt:
            raise
        except BaseException as e:  # noqa: BLE001 - anything leaving main() is the bug we look for
            escaped, trace = e, traceback.format_exc()
    # a warning is printed on stderr in a real process: it counts as stderr text
    shown = "".join(warnings.formatwarning(w.message, w.category, w.filename, w.lineno) for w in caught)
    return Outcome(code, out.getvalue(), shown + err.getvalue(), time.perf_counter() - t, escaped, trace)


def _reject_constant(name: str):
    raise ValueError(f"non-finite JSON constant {name}")


def _finite_json(x: object, where: str = "") -> None:
    if isinstance(x, float):
        assert math.isfinite(x), f"material.json{where}: non-finite {x}"
    elif isinstance(x, dict):
        for k, v in x.items():
            _finite_json(v, f"{where}.{k}")
    elif isinstance(x, list):
        for i, v in enumerate(x):
            _finite_json(v, f"{where}[{i}]")


def check_material(output: Path) -> None:
    """A complete, finite material directory at ``output``."""
    from torchmetal.material import load_material

    assert output.is_dir(), f"exit 0 but no material directory at {output}"
    text = (output / "material.json").read_text()
    meta = json.loads(text, parse_constant=_reject_constant)  # NaN/Infinity literals fail here
    # the phong/flakes parameters must be finite; the fit report may carry inf for "no value"
    # (e.g. a held-out error that was never computed): a report is text, not a parameter
    for key in ("phong", "flakes", "surface", "observed_flakes"):
        _finite_json(meta.get(key), f".{key}")
    m = load_material(output)  # checks texture, s, alpha
    for name in ("texture", "s", "alpha", "normals", "gloss_s", "gloss_alpha", "cluster_s", "cluster_alpha"):
        t = getattr(m, name, None)
        if t is not None:
            assert bool(np.isfinite(t.detach().numpy()).all()), f"material.{name}: non-finite values"
    assert m.texture.dim() == 3 and m.texture.shape[0] == 3 and m.texture.numel() > 0
    for f in output.rglob("*.npy"):
        a = np.load(f, allow_pickle=False)
        if a.dtype.kind == "f":
            assert bool(np.isfinite(a).all()), f"{f.name}: non-finite values"
    if m.flakes is not None:
        _finite_json(m.flakes.to_dict(), ".flakes(model)")


def check_outcome(o: Outcome, output: Path, tally: str) -> str:
    """Assert the property for one run; count it under ``tally``; returns how it ended."""
    if o.escaped is not None:
        TALLY[tally]["traceback"] += 1
        raise AssertionError(f"an exception escaped torchmetal.cli.main (a traceback for the user):\n{o.trace}")
    TIMES[tally].append(o.seconds)
    assert o.seconds < STALL_S, f"fit took {o.seconds:.1f} s on a tiny capture (a stall)"
    parent = output.parent
    leftovers = sorted(p.name for p in parent.iterdir() if p.name != output.name) if parent.is_dir() else []
    assert not leftovers, f"temporary files left beside the output: {leftovers}"
    if o.code == 0:
        check_material(output)
        kind = "material"
        if o.stderr.strip():  # allowed on success, but counted: warnings a user would see
            TALLY[tally + " (stderr on success)"][o.stderr.strip().splitlines()[0][-80:]] += 1
    else:
        assert o.code == 2, f"exit code {o.code}, expected 0 or 2; stderr: {o.stderr!r}"
        lines = o.stderr.strip().splitlines()
        assert len(lines) == 1, f"expected exactly one line on stderr, found {len(lines)}: {o.stderr!r}"
        line = lines[0]
        assert "Traceback" not in line
        assert line.startswith("torchmetal fit: error: "), line
        assert "expected" in line, f"the error does not say what was expected: {line!r}"
        assert not output.exists(), f"exit 2 but {output} exists (a partial material)"
        # a generic Python error class in the message means the bad input was not caught at the boundary
        reason = line[len("torchmetal fit: error: "):]
        assert reason.split(":")[0] not in ("ValueError", "OSError", "TypeError", "IndexError", "KeyError"), \
            f"an internal error reached the user unexplained: {line!r}"
        kind = "error"
        if "fit options" in tally or "real" in tally:  # valid captures: say which errors they got
            TALLY[tally + " (errors)"][re.sub(r"/\S*/", ".../", reason)[:110]] += 1
    TALLY[tally][kind] += 1
    return kind


def fresh_output(root: Path) -> Path:
    """An output path ``root/out/material`` whose parent exists and is empty."""
    parent = root / "out"
    parent.mkdir(parents=True, exist_ok=False)
    return parent / "material"


def summary_lines() -> list[str]:
    lines = []
    for name in sorted(TALLY):
        c = TALLY[name]
        t = TIMES[name]
        timing = f"; fit time mean {np.mean(t):.2f} s, max {max(t):.2f} s" if t else ""
        lines.append(f"{name}: {sum(c.values())} cases: " + " | ".join(f"{k} x{v}" for k, v in sorted(c.items())) + timing)
    return lines


def threads_one() -> None:
    """The fuzz runs share 2 cores with other work: one torch thread."""
    import torch

    if os.environ.get("OMP_NUM_THREADS") is None:
        torch.set_num_threads(1)
