"""Small captures and fault-injecting tasks for the scale tests."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import numpy as np

from torchmetal.scale.fit_many import verb_task


def make_captures(root: Path, n: int = 3, size: int = 32, shots: int = 6) -> list[Path]:
    """``n`` synthetic captures (different seeds) under ``root``."""
    from torchmetal.synth import synth_capture, write_synth

    out = []
    for k in range(n):
        path = root / f"cap{k}"
        write_synth(synth_capture(size=size, shots=shots, seed=10 + k, noise=0.003), path)
        out.append(path)
    return out


def kill_once_task(payload: dict) -> dict:
    """``verb_task``, but the first attempt on a capture whose name ends in '1' kills its own worker
    process (SIGKILL: no Python cleanup, as an out-of-memory kill)."""
    out = Path(payload["output"])
    marker = out.parent / f".killed-{out.name}"
    if out.name.endswith("1") and not marker.exists():
        marker.write_text("killed")
        os.kill(os.getpid(), signal.SIGKILL)
    return verb_task(payload)


def never_task(payload: dict) -> dict:
    """A task that must not run (resume tests)."""
    raise AssertionError(f"task ran for {payload['output']}")


def _strip_times(x):
    if isinstance(x, dict):
        return {k: _strip_times(v) for k, v in x.items() if "time" not in k}
    if isinstance(x, list):
        return [_strip_times(v) for v in x]
    return x


def material_fingerprint(material_dir: Path) -> tuple:
    """Everything of a material but its timings: the arrays' bytes and material.json."""
    meta = json.loads((material_dir / "material.json").read_text())
    arrays = tuple(sorted((f.name, np.load(f).tobytes()) for f in material_dir.glob("*.npy")))
    return arrays, json.dumps(_strip_times(meta), sort_keys=True)
