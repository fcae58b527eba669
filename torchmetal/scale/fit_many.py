"""``fit_many``: one ``torchmetal fit`` per capture, on a process pool or Ray.

Each job runs a command-line entry point (by default the ``fit`` verb of ``torchmetal.cli``,
named as a string so this layer imports nothing above it) inside a worker with its own argv:
``fit CAPTURE -o OUTDIR/<name> [fit options] -q``. A fit writes its material atomically, so a
job's output is either complete or absent, and resuming only looks at what is there.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import os
from pathlib import Path
from typing import Callable

from torchmetal.errors import InputError
from torchmetal.scale.many import Job, JobRecord, TaskError, run_many

FIT_ENTRY = "torchmetal.cli:main"


def verb_task(payload: dict) -> dict:
    """Run ``entry(argv)`` in this process with ``threads`` torch threads, stdout/stderr captured.

    payload: {"entry": "module:function", "argv": [...], "threads": int | None, "output": material dir}.
    Exit status 2 (bad input, a one-line reason) → :class:`TaskError` without retry; other
    non-zero → retried. Returns the material summary (:func:`material_summary`).
    """
    threads = payload.get("threads")
    if threads:
        import torch

        torch.set_num_threads(int(threads))
    module, func = payload["entry"].split(":")
    entry = getattr(importlib.import_module(module), func)
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        rc = int(entry(list(payload["argv"])) or 0)
    if rc != 0:
        lines = [ln for ln in err.getvalue().strip().splitlines() if ln.strip()]
        raise TaskError(lines[-1] if lines else f"exit status {rc}", retry=rc != 2)
    return material_summary(payload["output"])


def material_summary(material_dir: str | os.PathLike) -> dict:
    """rmse, held-out MSE (of the fit's held-out shot, for the model it kept), skipped stages and
    fit time from ``material.json``."""
    meta = json.loads((Path(material_dir) / "material.json").read_text())
    fit = meta.get("fit") or {}
    sel = fit.get("selection") or {}
    mse = sel.get("mse") or {}
    held = None
    if mse:
        held = mse.get("global") if sel.get("k", 1) == 1 else min(v for k, v in mse.items() if k != "global")
    return {"rmse": fit.get("rmse"), "heldout_mse": held, "hold": sel.get("hold"),
            "skipped": list(fit.get("skipped") or []), "fit_time_s": fit.get("total_time")}


def capture_jobs(captures: list[str | os.PathLike], outdir: str | os.PathLike, fit_args: list[str],
                 threads: int | None = None, entry: str = FIT_ENTRY) -> list[Job]:
    """One job per capture; the material goes to ``OUTDIR/<capture folder name>``."""
    if not captures:
        raise InputError("captures: expected at least one capture directory, found none")
    outdir = Path(outdir)
    jobs = []
    for cap in captures:
        cap = Path(cap)
        root = cap.parent if cap.suffix.lower() == ".json" and not cap.is_dir() else cap
        name = root.resolve().name
        out = outdir / name
        argv = ["fit", str(cap), "-o", str(out), *fit_args, "-q"]
        payload = {"entry": entry, "argv": argv, "threads": threads, "output": str(out)}
        key = {"entry": entry, "argv": argv}  # threads do not change a fit: not part of what resume compares
        jobs.append(Job(name, payload, str(out / "material.json"), key))
    names = [j.name for j in jobs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"captures: expected distinct folder names (each names its material), found {dup} twice")
    return jobs


def fit_many(
    captures: list[str | os.PathLike],
    outdir: str | os.PathLike,
    *,
    fit_args: list[str] = (),
    engine: str = "local",
    workers: int = 1,
    address: str | None = None,
    retries: int = 2,
    threads: int | None = 1,
    progress: bool = True,
    resume: bool = True,
    task: Callable[[dict], dict] = verb_task,
    entry: str = FIT_ENTRY,
) -> list[JobRecord]:
    """Fit every capture with ``torchmetal fit`` and the options ``fit_args``; see
    :func:`~torchmetal.scale.many.run_many` for retries, resume and the summary files.

    ``threads``: torch threads per fit (results do not depend on it: every reduction of the fit
    runs in a fixed order). ``task``: the job function (tests wrap :func:`verb_task`).
    """
    jobs = capture_jobs(captures, outdir, list(fit_args), threads, entry)
    return run_many(jobs, task, outdir, engine=engine, workers=workers, address=address, retries=retries,
                    progress=progress, resume=resume)
