"""Many independent tasks (one per capture) on an engine: retries, resume, summary.

``run_many(jobs, task, outdir, ...)`` runs ``task(job.payload)`` for every job on a local
process pool or Ray (:mod:`torchmetal.scale.engines`), at most ``workers`` at a time:

- a task that fails is retried up to ``retries`` times, every error kept (in the record and the
  summary); a :class:`TaskError` with ``retry=False`` (the input is bad: deterministic) is not;
- each finished job leaves ``OUTDIR/.fit-many/<name>.json`` (written atomically); a later run with
  the same key (the payload, less what does not change the output) finds it, with the job's output
  present, and does not redo the job;
- ``OUTDIR/summary.csv`` and ``summary.md`` (one row per job: status, attempts, time and what the
  task reported) are rewritten atomically after every job, so an interrupted run still has one.

Results never depend on the number of workers or on the engine: every task is independent and
its output is written by the task alone.
"""

from __future__ import annotations

import csv
import io
import json
import os
import time
from collections import deque
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

from torchmetal.errors import InputError
from torchmetal.io.images import atomic_write_bytes
from torchmetal.scale.engines import make_engine

RECORDS = ".fit-many"
SUMMARY_FIELDS = ("name", "status", "attempts", "time_s", "rmse", "heldout_mse", "skipped", "errors", "output")


class TaskError(RuntimeError):
    """A task failed with a one-line reason; ``retry=False`` when retrying cannot help."""

    def __init__(self, message: str, retry: bool = True) -> None:
        super().__init__(message)
        self.retry = retry

    def __reduce__(self):  # picklable across processes with both fields
        return (TaskError, (str(self), self.retry))


@dataclass
class Job:
    """One unit of work: ``name`` (unique; the output folder), the task's ``payload`` (JSON-able
    dict), the ``output`` path whose presence marks it done, and ``key``: what must match for a
    recorded job to count as this one (default: the payload)."""

    name: str
    payload: dict
    output: str
    key: dict | None = None

    @property
    def identity(self) -> dict:
        return self.payload if self.key is None else self.key


@dataclass
class JobRecord:
    """What happened to a job: status "ok" | "failed" | "resumed", attempts, the errors of each
    failed attempt, wall time of the successful attempt, and the task's result dict."""

    name: str
    status: str
    attempts: int = 0
    time_s: float = 0.0
    errors: list[str] = field(default_factory=list)
    result: dict = field(default_factory=dict)
    output: str = ""
    payload: dict = field(default_factory=dict)
    key: dict = field(default_factory=dict)


def _record_path(outdir: Path, name: str) -> Path:
    return outdir / RECORDS / f"{name}.json"


def _done_before(outdir: Path, job: Job) -> JobRecord | None:
    f = _record_path(outdir, job.name)
    try:
        rec = json.loads(f.read_text())
    except (OSError, ValueError):
        return None
    if rec.get("status") not in ("ok", "resumed") or rec.get("key") != job.identity or not Path(job.output).exists():
        return None
    return JobRecord(**{**rec, "status": "resumed", "attempts": 0})


def _write_record(outdir: Path, rec: JobRecord) -> None:
    atomic_write_bytes(_record_path(outdir, rec.name), json.dumps(asdict(rec), indent=1).encode())


def _describe(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}" if not isinstance(e, TaskError) else (text[0] if text else "")


def run_many(
    jobs: list[Job],
    task: Callable[[dict], dict],
    outdir: str | os.PathLike,
    *,
    engine: str = "local",
    workers: int = 1,
    address: str | None = None,
    retries: int = 2,
    progress: bool = True,
    resume: bool = True,
) -> list[JobRecord]:
    """Run ``task(job.payload)`` for every job; returns one :class:`JobRecord` per job, in order.

    Args:
        jobs: unique names (:class:`InputError` otherwise).
        task: a module-level function (it is pickled by reference to the workers) returning a
            JSON-able dict; it raises :class:`TaskError` (or anything) on failure.
        outdir: where records and the summary go.
        engine, workers, address: see :func:`~torchmetal.scale.engines.make_engine`.
        retries: extra attempts per job after a failure.
        progress: a tqdm bar over jobs.
        resume: skip jobs whose record says done with the same key and whose output exists.
    """
    _check_jobs(jobs, retries)
    outdir = Path(outdir)
    (outdir / RECORDS).mkdir(parents=True, exist_ok=True)
    records, todo = _resumed(jobs, outdir, resume)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc="fit-many", unit="capture")
    if todo:
        eng = make_engine(engine, workers, address)
        try:
            _run_jobs(eng, jobs, task, outdir, records, todo, workers=workers, retries=retries, bar=bar)
        finally:
            eng.close()
            if bar is not None:
                bar.close()
    elif bar is not None:
        bar.close()
    out = [r for r in records if r is not None]
    write_summary(outdir, out)
    return out


def _check_jobs(jobs: list[Job], retries: int) -> None:
    if not (isinstance(retries, int) and retries >= 0):
        raise InputError(f"retries: expected an int >= 0, found {retries!r}")
    names = [j.name for j in jobs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"jobs: expected unique names (the output folders), found {dup} more than once")


def _resumed(jobs: list[Job], outdir: Path, resume: bool) -> tuple[list[JobRecord | None], deque]:
    """(records: the jobs done before when ``resume``, else None; the indices of the jobs to run, in order)."""
    records: list[JobRecord | None] = [None] * len(jobs)
    todo = deque()
    for i, job in enumerate(jobs):
        prev = _done_before(outdir, job) if resume else None
        if prev is not None:
            records[i] = prev
        else:
            todo.append(i)
    return records, todo


def _run_jobs(eng: Any, jobs: list[Job], task: Callable[[dict], dict], outdir: Path, records: list[JobRecord | None],
              todo: deque, *, workers: int, retries: int, bar: Any) -> None:
    """Run the jobs ``todo`` on the engine, ``workers`` at a time, retrying failures; each finished job's record
    goes into ``records`` and to disk, with the summary."""
    attempts = [0] * len(jobs)
    errors: list[list[str]] = [[] for _ in jobs]
    started: dict[int, float] = {}
    inflight: dict[Any, int] = {}
    while todo or inflight:
        while todo and len(inflight) < workers:
            i = todo.popleft()
            attempts[i] += 1
            started[i] = time.perf_counter()
            inflight[eng.submit(task, jobs[i].payload)] = i
        for h in eng.wait(list(inflight)):
            i = inflight.pop(h)
            try:
                result = eng.result(h)
            except Exception as e:  # noqa: BLE001 — every failure is recorded, none is lost
                errors[i].append(f"attempt {attempts[i]}: {_describe(e)}")
                if getattr(e, "retry", True) and attempts[i] <= retries:
                    todo.append(i)
                    continue
                records[i] = JobRecord(jobs[i].name, "failed", attempts[i], 0.0, errors[i], {}, jobs[i].output,
                                       jobs[i].payload, jobs[i].identity)
            else:
                records[i] = JobRecord(jobs[i].name, "ok", attempts[i], time.perf_counter() - started[i],
                                       errors[i], dict(result or {}), jobs[i].output, jobs[i].payload,
                                       jobs[i].identity)
            _write_record(outdir, records[i])
            write_summary(outdir, [r for r in records if r is not None])
            if bar is not None:
                bar.update(1)
                bar.set_postfix(last=f"{jobs[i].name}:{records[i].status}")


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (list, tuple)):
        return "; ".join(str(x) for x in v)
    return str(v)


def summary_rows(records: list[JobRecord]) -> list[dict[str, str]]:
    """One flat row per record (the columns of ``SUMMARY_FIELDS``)."""
    rows = []
    for r in records:
        res = r.result
        rows.append({
            "name": r.name, "status": r.status, "attempts": str(r.attempts), "time_s": _fmt(float(r.time_s)),
            "rmse": _fmt(res.get("rmse")), "heldout_mse": _fmt(res.get("heldout_mse")),
            "skipped": _fmt(res.get("skipped")), "errors": _fmt(r.errors), "output": r.output,
        })
    return rows


def write_summary(outdir: str | os.PathLike, records: list[JobRecord]) -> tuple[Path, Path]:
    """``OUTDIR/summary.csv`` and ``summary.md`` from the records (atomic writes)."""
    outdir = Path(outdir)
    rows = summary_rows(records)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_FIELDS, lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    atomic_write_bytes(outdir / "summary.csv", buf.getvalue().encode())
    counts = {s: sum(r.status == s for r in records) for s in ("ok", "resumed", "failed")}
    lines = [f"# fit-many summary: {len(records)} captures — {counts['ok']} fitted, {counts['resumed']} done before "
             f"(resumed), {counts['failed']} failed", "",
             "| " + " | ".join(SUMMARY_FIELDS) + " |", "|" + "---|" * len(SUMMARY_FIELDS)]
    for row in rows:
        lines.append("| " + " | ".join(row[k].replace("|", "\\|").replace("\n", " ") for k in SUMMARY_FIELDS) + " |")
    md = outdir / "summary.md"
    atomic_write_bytes(md, ("\n".join(lines) + "\n").encode())
    return outdir / "summary.csv", md
