"""The state of one fit: stage timers, the iteration history, what was skipped, the choices made on
left-out shots, the progress bar."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from torchmetal.fit.result import IterationCounts


class FitRun:
    """Timers, history, skipped stages, decisions and the progress bar of one fit."""

    def __init__(self, progress: bool) -> None:
        self.times: dict[str, float] = {}
        self.history: list[dict] = []
        self.iterations = IterationCounts()
        self.skipped: list[str] = []
        self.decisions: list[dict] = []  # Decision.to_dict() of each choice made on left-out shots, in order
        self.plan = None  # the ShotPlan those choices held out (torchmetal.select.plan), once made
        self.bar = None
        if progress:
            from tqdm.auto import tqdm  # deferred: in a notebook tqdm.auto imports ipywidgets

            self.bar = tqdm(desc="fit_phong", unit="it", leave=False)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.times[name] = self.times.get(name, 0.0) + time.perf_counter() - t0

    def log(self, stage: str, it: int, rmse: float, active: float, pixels: int) -> None:
        self.history.append({"stage": stage, "iter": int(it), "rmse": float(rmse), "active": float(active),
                             "pixels": int(pixels)})
        self.iterations[stage] = max(self.iterations.get(stage, 0), int(it))
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(stage=stage, rmse=f"{rmse:.3g}")

    def logger(self, stage: str, pixels: int) -> Callable[[int, float, float], None]:
        return lambda it, rmse, active: self.log(stage, it, rmse, active, pixels)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
