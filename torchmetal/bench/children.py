"""Child processes of ``torchmetal bench``: one per job (``--isolate``) or one long-lived
:class:`Server` running jobs in turn (``--quick``), with the thread count passed in the environment."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from torchmetal.bench.worker import MARKER

THREADS_ENV = "TORCHMETAL_BENCH_THREADS"


def _env(threads: int | None = None) -> dict:
    env = dict(os.environ)
    threads = threads or (int(env[THREADS_ENV]) if env.get(THREADS_ENV) else None)
    if threads:
        for k in (THREADS_ENV, "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env[k] = str(threads)
    root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("PYTHONWARNINGS", "ignore")
    return env


class Server:
    """One long-lived worker child (``--serve``) that runs jobs one after another.

    Used by ``--quick``: one interpreter start for the whole benchmark. A job that exceeds its
    timeout kills the child; the next job starts a fresh one.
    """

    def __init__(self, threads: int | None = None) -> None:
        self.proc: subprocess.Popen | None = None
        self.threads = threads
        self._buf = b""

    def _start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "torchmetal.bench.worker", "--serve"], env=_env(self.threads),
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
        )
        self._buf = b""

    def run(self, task: str, cfg: dict, timeout: float) -> dict:
        import selectors

        if self.proc is None or self.proc.poll() is not None:
            self._start()
        assert self.proc is not None and self.proc.stdin is not None and self.proc.stdout is not None
        t0 = time.perf_counter()
        try:
            self.proc.stdin.write((json.dumps([task, cfg]) + "\n").encode())
            self.proc.stdin.flush()
        except BrokenPipeError:
            self.close()
            return {"error": "worker process died"}
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        fd = self.proc.stdout.fileno()
        try:
            while True:
                if b"\n" in self._buf:
                    line, self._buf = self._buf.split(b"\n", 1)
                    text = line.decode(errors="replace")
                    if text.startswith(MARKER):
                        r = json.loads(text[len(MARKER):])
                        r.setdefault("child_s", time.perf_counter() - t0)
                        return r
                    continue
                left = timeout - (time.perf_counter() - t0)
                if left <= 0 or not sel.select(left):
                    self.close()
                    return {"error": f"timed out after {timeout:.0f} s"}
                chunk = os.read(fd, 1 << 16)
                if not chunk:
                    self.close()
                    return {"error": "worker process exited"}
                self._buf += chunk
        finally:
            sel.close()

    def close(self) -> None:
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.kill()
            self.proc.wait()
            for f in (self.proc.stdin, self.proc.stdout):
                if f is not None:
                    f.close()
        self.proc = None


def run_jobs(jobs: list[tuple[str, dict]], *, isolate: bool, timeout: float, log=None,
             server: Server | None = None, threads: int | None = None) -> list[dict]:
    """Run ``[(task, cfg), ...]``: one child process per job (``isolate``), else on ``server``.

    A child that times out or dies yields ``{"error": ...}`` for that job; the rest still run.
    """
    results: list[dict] = []
    own = None
    if not isolate and server is None:
        server = own = Server(threads)
    try:
        for task, cfg in jobs:
            if isolate:
                r = _run_isolated(task, cfg, timeout, threads)
            else:
                r = server.run(task, cfg, timeout)
            results.append(r)
            if log:
                log(task, cfg, r)
    finally:
        if own is not None:
            own.close()
    return results


def _run_isolated(task: str, cfg: dict, timeout: float, threads: int | None = None) -> dict:
    with tempfile.TemporaryDirectory(prefix="tmbench-") as d:
        res_path = Path(d) / "result.json"
        cmd = [sys.executable, "-m", "torchmetal.bench.worker", task, json.dumps(cfg), str(res_path)]
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, env=_env(threads), capture_output=True, text=True, timeout=timeout)
            failure = None if proc.returncode == 0 else f"child exited {proc.returncode}: {proc.stderr.strip()[-300:]}"
        except subprocess.TimeoutExpired:
            failure = f"timed out after {timeout:.0f} s"
        if res_path.exists() and failure is None:
            r = json.loads(res_path.read_text())
            r.setdefault("child_s", time.perf_counter() - t0)
            return r
        return {"error": failure or "child produced no result"}
