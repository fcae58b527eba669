"""Where tasks run: a local process pool or a Ray cluster, behind one small interface.

An engine runs ``task(payload)`` somewhere and hands back a handle; :meth:`wait` returns the
handles that finished, :meth:`result` their value or raises their error. Scheduling, retries and
bookkeeping live in :mod:`torchmetal.scale.many`, identical for both engines.

- ``local``: :class:`concurrent.futures.ProcessPoolExecutor` with the ``spawn`` start method (no
  fork of a process that holds torch threads). A worker killed from outside breaks the whole
  pool (every task in flight fails with ``BrokenProcessPool``); the pool is rebuilt and the tasks
  are retried.
- ``ray``: one Ray task per payload (``num_cpus=1``, Ray's own retries off so that every failure
  reaches the scheduler and is recorded); ``address=None`` starts a local cluster with
  ``workers`` CPUs, otherwise joins ``address``. Ray is an optional extra.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
from typing import Any, Callable

from torchmetal.errors import InputError

ENGINES = ("local", "ray")


class LocalEngine:
    """A process pool of ``workers`` processes."""

    name = "local"

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self._pool = self._new_pool()

    def _new_pool(self) -> cf.ProcessPoolExecutor:
        return cf.ProcessPoolExecutor(self.workers, mp_context=mp.get_context("spawn"))

    def submit(self, task: Callable[[Any], Any], payload: Any) -> cf.Future:
        try:
            return self._pool.submit(task, payload)
        except cf.process.BrokenProcessPool:  # a worker died since the last submit
            self.restart()
            return self._pool.submit(task, payload)

    def wait(self, handles: list) -> list:
        done, _ = cf.wait(handles, return_when=cf.FIRST_COMPLETED)
        return [h for h in handles if h in done]  # submission order: deterministic bookkeeping

    def result(self, handle: cf.Future) -> Any:
        try:
            return handle.result()
        except cf.process.BrokenProcessPool as e:
            raise WorkerLost(f"worker process died ({e})") from None

    def restart(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._pool = self._new_pool()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class RayEngine:
    """Ray tasks on a local cluster (``address=None``) or the cluster at ``address``."""

    name = "ray"

    def __init__(self, workers: int, address: str | None = None) -> None:
        try:
            import ray
        except ImportError:
            raise InputError("engine 'ray': expected the ray package (pip install torchmetal[ray]), found it "
                             "missing; use --engine local") from None
        self._ray = ray
        self._own = not ray.is_initialized()
        if self._own:
            if address is None:
                ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
            else:
                ray.init(address=address, include_dashboard=False, log_to_driver=False)
        self._remote = ray.remote(num_cpus=1, max_retries=0)(_call)

    def submit(self, task: Callable[[Any], Any], payload: Any) -> Any:
        return self._remote.remote(task, payload)

    def wait(self, handles: list) -> list:
        ready, _ = self._ray.wait(handles, num_returns=1)
        ready_ids = {r.hex() for r in ready}
        return [h for h in handles if h.hex() in ready_ids]

    def result(self, handle: Any) -> Any:
        ray = self._ray
        try:
            return ray.get(handle)
        except ray.exceptions.RayTaskError as e:  # the task raised: re-raise its own exception
            cause = e.as_instanceof_cause()
            raise (cause.cause if getattr(cause, "cause", None) is not None else cause) from None
        except ray.exceptions.RayError as e:  # worker crashed, node died, object lost
            raise WorkerLost(f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}") from None

    def restart(self) -> None:
        pass  # Ray replaces dead workers itself

    def close(self) -> None:
        if self._own:
            self._ray.shutdown()


class WorkerLost(RuntimeError):
    """The process running a task died (killed, out of memory): always worth a retry."""


def _call(task: Callable[[Any], Any], payload: Any) -> Any:
    return task(payload)


def make_engine(engine: str, workers: int, address: str | None = None) -> LocalEngine | RayEngine:
    """The engine named ``engine`` ("local" or "ray") with ``workers`` concurrent tasks."""
    if engine not in ENGINES:
        raise InputError(f"engine: expected one of {list(ENGINES)}, found {engine!r}")
    if not (isinstance(workers, int) and workers >= 1):
        raise InputError(f"workers: expected an int >= 1, found {workers!r}")
    if address is not None and engine != "ray":
        raise InputError(f"address: only with engine 'ray', found engine {engine!r}")
    return LocalEngine(workers) if engine == "local" else RayEngine(workers, address)
