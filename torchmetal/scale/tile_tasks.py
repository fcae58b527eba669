"""The tiled fit's work per tile, as tasks: in this process, on a process pool or on Ray.

Every pass of the tiled fit (:mod:`torchmetal.scale.tiled`) maps one task over the tile list
and reduces the results **in tile order** (results that arrive early wait in a buffer), so the
sums are the same whatever the engine and the number of workers. A task gets the capture's path
and reopens it (once per worker process); the texture pass writes its tile into memory-mapped
files, so workers need the scratch folder on a file system they share (one machine, or a shared
mount on a cluster). A task whose worker dies is resubmitted (up to ``RETRIES`` times).

Tasks (``payload["kind"]``):
- ``"sums"``: the per-tile constants: element sums of A, the observation count, the first LM
  evaluation's statistics, Σw·a² statistics (:class:`~torchmetal.scale.tiled_texture.SeenStats`),
  whether the normals are flat, cluster areas.
- ``"stats"``: the projected sums (6, K, 3) at α (:func:`~torchmetal.fit.refine.spec_sums`).
- ``"relabel"``: each pixel's cluster after the LM (:func:`~torchmetal.fit.clusters.relabel`), written
  into the labels memmap; returns how many moved.
- ``"low_bits"``: the radix median's second histogram.
- ``"texture"``: the tile's texture and unobserved texels, written into the memmaps.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from torchmetal.fit.clusters import relabel
from torchmetal.fit.problem import build_observations
from torchmetal.fit.refine import spec_sums, texture_map
from torchmetal.geometry import is_flat
from torchmetal.scale.engines import WorkerLost
from torchmetal.scale.tiled_texture import SeenStats, unobserved_tile
from torchmetal.scale.tiles import TiledCapture

RETRIES = 2
_OPEN: dict[str, TiledCapture] = {}  # captures opened in this process, by path


def _capture(path: str) -> TiledCapture:
    if path not in _OPEN:
        _OPEN[path] = TiledCapture(path)
    return _OPEN[path]


def tile_task(p: dict) -> Any:
    """Run one tile's task (see the module docstring); ``p`` is a picklable dict."""
    threads = p.get("threads")
    if threads:
        torch.set_num_threads(int(threads))
    cap = _capture(p["capture"])
    rows, cols = p["rows"], p["cols"]
    kind = p["kind"]
    ref, labeler = p.get("ref"), p.get("labeler")
    if kind == "low_bits":
        ref = labeler = None
    obs = build_observations(cap, dtype=getattr(torch, p["dtype"]), chunk=p["chunk"], ref=ref, labeler=labeler,
                             with_stats=kind == "sums" and ref is not None, window=(rows, cols))
    k = 1 if ref is None else ref.k
    if kind == "sums":
        seen = SeenStats()
        seen.add(obs.saa)
        nrm = cap.normals[:, rows, cols]
        return {"A": obs.element_sum(obs.A, k), "n": float(obs.n.sum()),
                "first": None if ref is None else obs.first_stats[0], "seen": seen,
                "flat": is_flat(nrm),
                "area": torch.bincount(obs.labels, minlength=k).double() if labeler is not None else None}
    if kind == "stats":
        return spec_sums(obs, p["alpha"])[0]
    if kind == "relabel":  # each pixel to the element that explains it best (fit.clusters.relabel), into labels_file
        labels, moved = relabel(obs, p["s"], p["alpha"], p["per_obs"])
        lab = np.load(p["labels_file"], mmap_mode="r+")
        lab[rows, cols] = labels.reshape(obs.height, obs.width).numpy()
        lab.flush()
        return moved
    if kind == "low_bits":
        return SeenStats.low_bits(obs.saa, p["bucket"])
    if kind == "texture":
        if p["s"] is None:
            tex = torch.where(obs.saa > 0, obs.d0, obs.fallback)
        else:
            tex = texture_map(obs, p["s"], spec_sums(obs, p["alpha"])[1])
        bad = unobserved_tile(obs.saa, cap.mask[..., rows, cols].reshape(-1), p["median"])
        hw = (obs.height, obs.width)
        raw = np.load(p["raw_file"], mmap_mode="r+")
        raw[rows, cols] = tex.reshape(3, *hw).permute(1, 2, 0).numpy()
        raw.flush()
        badf = np.load(p["bad_file"], mmap_mode="r+")
        badf[rows, cols] = bad.reshape(3, *hw).permute(1, 2, 0).numpy()
        badf.flush()
        if p.get("labels_file"):
            lab = np.load(p["labels_file"], mmap_mode="r+")
            lab[rows, cols] = obs.labels.reshape(*hw).numpy()
            lab.flush()
        del raw, badf
        return int(bad.any(0).sum())
    raise ValueError(f"tile_task: unknown kind {kind!r}")


class TilePasses:
    """Map :func:`tile_task` over the tiles, results in tile order.

    ``engine`` None runs the tasks here, in order; otherwise an engine of
    :mod:`torchmetal.scale.engines` with at most 2 × ``workers`` tasks in flight.
    """

    def __init__(self, tiles: list[tuple[slice, slice]], base: dict, engine: Any = None, workers: int = 1,
                 bar: Any = None) -> None:
        self.tiles, self.base, self.engine, self.workers, self.bar = tiles, base, engine, workers, bar
        self.passes = 0

    def map(self, kind: str, **kw: Any) -> Iterator[Any]:
        self.passes += 1
        payloads = [{**self.base, **kw, "kind": kind, "rows": r, "cols": c} for r, c in self.tiles]
        if self.engine is None:
            for p in payloads:
                yield tile_task(p)
                if self.bar is not None:
                    self.bar.update(1)
            return

        eng, n = self.engine, len(payloads)
        inflight: dict = {}
        ready: dict[int, object] = {}
        attempts = [0] * n
        queue = list(range(n))[::-1]
        nxt = 0
        while nxt < n:
            while queue and len(inflight) + len(ready) < 2 * self.workers:
                i = queue.pop()
                attempts[i] += 1
                inflight[eng.submit(tile_task, payloads[i])] = i
            for h in eng.wait(list(inflight)):
                i = inflight.pop(h)
                try:
                    ready[i] = eng.result(h)
                except WorkerLost:  # a pool loses every task in flight with its worker: resubmit them all
                    if attempts[i] > RETRIES:
                        raise
                    queue += [i, *inflight.values()]
                    inflight.clear()
                    eng.restart()
                    break
                if self.bar is not None:
                    self.bar.update(1)
            while nxt in ready:
                yield ready.pop(nxt)
                nxt += 1
