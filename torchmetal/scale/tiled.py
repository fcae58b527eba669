"""The Phong fit of a capture too large for memory, tile by tile (``fit --tile N``).

The in-memory fit (:func:`torchmetal.fit.fit_phong`, scheme "refine") has two parts:

1. decisions on strided pixel subsamples (≤ ``sub_pixels`` pixels): the paper's scheme as init,
   variable projection, highlight evidence, global vs clustered specular. Here they run on the
   same subsample, read from the memory-mapped files (:class:`~torchmetal.scale.tiles.TiledCapture`),
   with the same functions — the same values bit for bit.
2. the full-resolution solve, where texture and s are projected out and LM runs on β = log α:
   everything it needs from the pixels is a sum over pixels of per-pixel statistics
   (:func:`~torchmetal.fit.refine.spec_sums`). Here each LM evaluation is a pass over the tiles:
   each tile's observations are built (:func:`~torchmetal.fit.problem.build_observations` with a
   ``window``), its statistics computed, and the statistics added in float64 in a fixed tile
   order — so the result does not depend on how many workers computed the tiles. A last pass
   solves the texture of each tile in closed form and writes it to a memory-mapped file.

Memory is that of one tile's observations (~100 bytes per pixel and shot), never the capture's.
What the tiled fit does not do: the flake stage (detection needs whole images: it is skipped and
the report says so), scheme "paper", robust weights and outlier masks, and the inpainting of
texels no shot observes (refused with a one-line error; fit such captures in memory).
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchmetal.config import FitConfig, check_tiled
from torchmetal.errors import FitError, InputError
from torchmetal.fit.clusters import RELABEL_ROUNDS, LabelMap
from torchmetal.fit.decisions import subsample_decisions
from torchmetal.fit.lm import LMEval, levenberg_marquardt
from torchmetal.fit.problem import Reference, compute_dtype
from torchmetal.fit.refine import ALPHA_MIN, beta_bounds, element_terms, pinned_terms
from torchmetal.fit.result import FitResult
from torchmetal.fit.run import FitRun
from torchmetal.pipeline import PipelineResult
from torchmetal.scale.engines import make_engine
from torchmetal.scale.tile_tasks import _OPEN, TilePasses
from torchmetal.scale.tiled_texture import SeenStats, fill_tiles
from torchmetal.scale.tiles import TiledCapture, convert_capture, is_tiled

if TYPE_CHECKING:
    import os

SPECULARS = ("auto", "global", "clustered", "none")


def tile_grid(height: int, width: int, tile: int) -> list[tuple[slice, slice]]:
    """Row-major tiles of at most ``tile`` × ``tile`` pixels: the fixed reduction order."""
    if not (isinstance(tile, int) and tile >= 1):
        raise InputError(f"tile: expected an int >= 1 (pixels per tile side), found {tile!r}")
    return [(slice(r, min(height, r + tile)), slice(c, min(width, c + tile)))
            for r in range(0, height, tile) for c in range(0, width, tile)]


def _solve_specular(passes: TilePasses, dt: torch.dtype, beta0: Tensor, first: Tensor, A: Tensor, *, tol: float,
                    max_iters: int, s_fixed: Tensor | None, beta_fixed: Tensor | None, on_iter) -> tuple:
    """LM on β (K, 3) with per-element sums reduced over tiles — :func:`~torchmetal.fit.refine.fit_specular`'s
    iteration, its evaluation a pass over the tiles. Returns (s, α, cost, LM result)."""
    k = int(beta0.shape[0])
    floor = (0.01 * torch.finfo(dt).eps * A).reshape(-1)

    def evaluate(stats: Tensor) -> LMEval:
        s, cost, g, h = element_terms(stats, A, s_fixed=s_fixed)
        return LMEval(cost.reshape(-1), g.reshape(-1, 1), h.reshape(-1, 1, 1), aux=s.reshape(-1), floor=floor)

    def oracle(x: Tensor) -> LMEval:
        alpha = torch.exp(x.view(k, 3))
        total = torch.zeros(6, k, 3, dtype=torch.float64)
        for stats in passes.map("stats", alpha=alpha):  # tile order: the same sums for any number of workers
            total += stats
        return evaluate(total)

    lo, hi, x0 = beta_bounds(beta0.cpu(), beta_fixed)
    ev0 = evaluate(first) if bool((x0 == beta0.reshape(-1, 1).to(torch.float64)).all()) else oracle(x0)
    on_iter(0, ev0)
    res = levenberg_marquardt(oracle, x0, lower=lo, upper=hi, tol=tol, xtol=tol, max_iters=max_iters,
                              merge=lambda new, old, acc: torch.where(acc, new, old), first=ev0,
                              on_iter=lambda it, x, ev, done: on_iter(it, ev))
    return res.eval.aux.view(k, 3), torch.exp(res.x.view(k, 3)), res.eval.cost.view(k, 3), res


@dataclass(frozen=True)
class TiledOptions:
    """What :func:`fit_tiled` was asked, checked: the fit's options (as :func:`~torchmetal.fit.fit_phong`;
    ``chunk`` is its ``max_pixels_per_chunk``), where the result's files go and where the tile tasks run."""

    tile: int
    specular: str
    tol: float
    max_iters: int
    clusters: tuple[int, ...]
    chunk: int
    sub_pixels: int
    select_pixels: int
    seed: int
    scratch: Path
    engine: object | None  # a torchmetal.scale.engines engine; None: the tasks run in this process
    workers: int
    threads: int | None


def fit_tiled(
    capture: TiledCapture | str,
    *,
    tile: int = 1024,
    specular: str = "auto",
    tol: float = 1e-6,
    max_iters: int = 100,
    clusters: tuple[int, ...] = (2, 3, 4),
    max_pixels_per_chunk: int = 4096,
    sub_pixels: int = 1 << 16,
    select_pixels: int = 1 << 13,
    seed: int = 0,
    progress: bool = False,
    scratch: str | Path | None = None,
    engine: str | None = None,
    workers: int = 1,
    address: str | None = None,
    threads: int | None = None,
) -> FitResult:
    """:func:`~torchmetal.fit.fit_phong` (scheme "refine", least squares) of a tiled capture, tile by tile.

    Args:
        capture: a :class:`TiledCapture` or its directory (``.npy`` images; see
            :func:`~torchmetal.scale.tiles.convert_capture`).
        tile: tile side in pixels (memory ∝ tile² × shots).
        specular, tol, max_iters, clusters, max_pixels_per_chunk, sub_pixels, select_pixels, seed:
            as :func:`~torchmetal.fit.fit_phong`.
        scratch: folder for the memory-mapped texture (and normals / labels) of the result
            (default: a new temporary folder); keep it until the result is saved.
        engine, workers, address: run the tile tasks here (``engine=None``, the default), on a
            process pool (``"local"``) or on Ray (``"ray"``), ``workers`` at a time
            (:mod:`torchmetal.scale.tile_tasks`); the result does not depend on it.
        threads: torch threads per tile task on an engine (default: CPU cores / workers).

    Returns:
        :class:`~torchmetal.fit.FitResult` whose texture (3, H, W) is a view of a memory-mapped
        file in ``scratch``; ``report()["tiled"]`` has the tile count and passes.
    """
    cap = capture if isinstance(capture, TiledCapture) else TiledCapture(capture)
    _check_tiled_args(cap, tile=tile, workers=workers, specular=specular, tol=tol, max_iters=max_iters)
    scratch = Path(scratch) if scratch is not None else Path(tempfile.mkdtemp(prefix="torchmetal-tiled-"))
    scratch.mkdir(parents=True, exist_ok=True)
    run = FitRun(False)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(desc="fit --tile", unit="tile", leave=False)
    eng, threads = _start_engine(engine, workers, address, threads)
    try:
        opt = TiledOptions(tile=tile, specular=specular, tol=tol, max_iters=max_iters, clusters=tuple(clusters),
                           chunk=max_pixels_per_chunk, sub_pixels=sub_pixels, select_pixels=select_pixels, seed=seed,
                           scratch=scratch, engine=eng, workers=workers, threads=threads)
        return _fit(cap, run, bar, opt)
    finally:
        if bar is not None:
            bar.close()
        if eng is not None:
            eng.close()


def _check_tiled_args(cap: TiledCapture, *, tile: int, workers: int, specular: str, tol: float, max_iters: int) -> None:
    tile_grid(cap.height, cap.width, tile)  # checks tile
    if not (isinstance(workers, int) and workers >= 1):
        raise InputError(f"workers: expected an int >= 1, found {workers!r}")
    if specular not in SPECULARS:
        raise InputError(f"specular: expected one of {list(SPECULARS)}, found {specular!r}")
    if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
        raise InputError(f"tol: expected a finite number > 0, found {tol!r}")
    if not (isinstance(max_iters, int) and max_iters >= 1):
        raise InputError(f"max_iters: expected an int >= 1, found {max_iters!r}")


def _start_engine(engine: str | None, workers: int, address: str | None, threads: int | None) -> tuple[object | None, int | None]:
    """(the engine of the tile tasks, None: this process; torch threads per task, default CPU cores / workers)."""
    eng = None
    if engine is not None:
        import os

        eng = make_engine(engine, workers, address)
        threads = threads or max(1, (os.cpu_count() or 1) // workers)
    return eng, threads


def _subsample_decisions(cap, run: FitRun, *, specular, tol, max_iters, clusters, chunk, sub_pixels, select_pixels, seed):
    """Steps 1–4b of ``fit_phong``'s refine scheme (least squares, Phong) on the strided subsamples, by
    :func:`~torchmetal.fit.decisions.subsample_decisions` itself: returns (spec fit or None, labeler or None,
    s_fixed or None, selection info or None). Gloss maps that win are refused (one line)."""
    d = subsample_decisions(cap, run, specular=specular, tol=tol, max_iters=max_iters, robust=None, outliers=None,
                            clusters=clusters, chunk=chunk, sub_pixels=sub_pixels, select_pixels=select_pixels, seed=seed,
                            colour=False)
    if d.use_maps:
        raise FitError("fit --tile: gloss maps win on the held-out shot, and the tiled fit does not fit them (their "
                       "smoothness prior couples all pixels); fit this capture in memory or with --specular global")
    sel = d.sel
    info = None if sel is None else {"k": sel.k, "hold": sel.hold, "mse": sel.mse, "reason": sel.reason,
                                     "relabel": sel.relabel}
    run.maps_info = d.maps_info
    return d.spec, d.labeler, d.s_fixed, info


class _Sums(NamedTuple):
    """The "sums" pass reduced in tile order."""

    A: Tensor  # element sums (K, 3)
    first: Tensor  # the first LM evaluation's stats (6, K, 3)
    n_total: float  # observation count
    seen: SeenStats  # Σw·a² statistics
    flat: bool  # whether the normals are flat
    area: Tensor  # cluster areas (K,)


def _sums(passes: TilePasses, k: int, with_spec: bool, with_labels: bool) -> _Sums:
    """The "sums" pass reduced in tile order (:class:`_Sums`)."""
    A = torch.zeros(k, 3, dtype=torch.float64)
    first = torch.zeros(6, k, 3, dtype=torch.float64)
    n_total, seen_stats, flat = 0.0, SeenStats(), True
    area = torch.zeros(k, dtype=torch.float64)
    for part in passes.map("sums"):  # in tile order
        A += part["A"]
        n_total += part["n"]
        if with_spec:
            first += part["first"]
        seen_stats.merge(part["seen"])
        flat = flat and part["flat"]
        if with_labels:
            area += part["area"]
    return _Sums(A, first, n_total, seen_stats, flat, area)


def _memmap(path: Path, shape: tuple[int, ...], dtype) -> np.memmap:
    return np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)


def _fit(cap: TiledCapture, run: FitRun, bar, opt: TiledOptions) -> FitResult:
    """:func:`fit_tiled` after its checks: the subsample decisions, the sums pass, the LM on β over tile
    passes (:func:`_specular`), the texture pass, the result."""
    dt = compute_dtype(cap.images)
    h, w = cap.height, cap.width
    spec, labeler, s_fixed, sel_info = _subsample_decisions(
        cap, run, specular=opt.specular, tol=opt.tol, max_iters=opt.max_iters, clusters=opt.clusters, chunk=opt.chunk,
        sub_pixels=opt.sub_pixels, select_pixels=opt.select_pixels, seed=opt.seed)
    k = 1 if spec is None else spec.k
    ref = None if spec is None else Reference(spec.s, spec.alpha)
    tiles = tile_grid(h, w, opt.tile)
    _OPEN[str(cap.root)] = cap  # in-process tasks reuse this capture
    base = {"capture": str(cap.root), "dtype": str(dt).removeprefix("torch."), "chunk": opt.chunk, "ref": ref,
            "labeler": labeler, "threads": opt.threads}
    passes = TilePasses(tiles, base, opt.engine, opt.workers, bar)

    # pass 1: per-pixel constants → element sums, the first LM evaluation, what the texture step needs
    with run.stage("geometry"):
        sums = _sums(passes, k, spec is not None, labeler is not None)
    if sums.seen.needs_median():  # the exact median of Σw·a² (one more pass); else any value below it works
        med = sums.seen.median(lambda bucket: passes.map("low_bits", bucket=bucket))
    else:
        med = sums.seen.hi.clone()
    n_obs = max(1.0, sums.n_total)

    status, cost, s, alpha, area = "converged", None, None, None, sums.area
    if spec is not None:
        relabel = labeler is not None and sel_info["relabel"]
        s, alpha, cost, area, status = _specular(passes, run, spec, labeler, s_fixed, relabel, sums, dt, opt, (h, w))

    tex_file, lab_file = _texture(passes, run, tiles, (h, w), s, alpha, med, labeler is not None, opt.scratch)
    if spec is None:
        rmse = math.sqrt(float(sums.A.sum()) / n_obs)
        run.log("texture", 0, rmse, 1.0, h * w)
    else:
        rmse = math.sqrt(float(cost.sum()) / n_obs)
    common = dict(texture=torch.from_numpy(tex_file).permute(2, 0, 1), normals=_normals(cap, tiles, sums.flat, dt, opt.scratch),
                  size=tuple(float(v) for v in cap.size), history=run.history, stage_times=run.times,
                  iterations=run.iterations, skipped=run.skipped, flat=sums.flat, status=status, rmse=rmse,
                  scheme="refine", selection=sel_info)
    if spec is None:
        z = torch.zeros(3, dtype=dt)
        result = FitResult(s=z, alpha=torch.full_like(z, ALPHA_MIN), specular="none", **common)
    elif k == 1:
        result = FitResult(s=s[0].to(dt), alpha=alpha[0].to(dt), specular="global", **common)
    else:
        frac = area / area.sum().clamp_min(1.0)
        result = FitResult(s=(frac @ s).to(dt), alpha=(frac @ alpha).to(dt), spec_labels=torch.from_numpy(lab_file),
                           cluster_s=s.to(dt), cluster_alpha=alpha.to(dt), specular="clustered", **common)
    result.maps_selection = getattr(run, "maps_info", None)
    result.tiled = {"tile": opt.tile, "tiles": len(tiles), "passes": passes.passes, "scratch": str(opt.scratch),
                    "engine": "here" if opt.engine is None else opt.engine.name, "workers": opt.workers}
    if not bool(torch.isfinite(result.s).all() and torch.isfinite(result.alpha).all()) or not math.isfinite(rmse):
        raise FitError("fit --tile: expected finite fit values, found NaN/Inf (non-finite residuals)")
    return result


def _specular(passes: TilePasses, run: FitRun, spec, labeler, s_fixed: Tensor | None, relabel: bool, sums: _Sums,
              dt: torch.dtype, opt: TiledOptions, grid: tuple[int, int]) -> tuple:
    """The LM on β over tile passes from the subsample's ``spec``; with clusters and ``relabel``, then the
    rounds of :func:`~torchmetal.fit.clusters.relabel_pixels`, each a pass over the tiles, a new sums pass
    and the LM again. Returns (s, α, cost, cluster areas, LM status)."""
    h, w = grid
    k = spec.k
    ref = passes.base["ref"]  # the subsample's reference: the texture pass's fallback
    n_obs = max(1.0, sums.n_total)
    s_fix = b_fix = None
    if labeler is not None:  # clusters without evidence keep the global terms
        s_fix, b_fix = pinned_terms(spec.pinned, spec.s, spec.alpha)
    elif s_fixed is not None:
        s_fix = s_fixed

    def log(it: int, ev: LMEval) -> None:
        run.log("refine", it, math.sqrt(float(ev.cost.sum()) / n_obs), 1.0, h * w)

    with run.stage("refine"):
        s, alpha, cost, res = _solve_specular(passes, dt, torch.log(spec.alpha), sums.first, sums.A, tol=opt.tol,
                                              max_iters=opt.max_iters, s_fixed=s_fix, beta_fixed=b_fix, on_iter=log)
    area = sums.area
    if relabel:  # fit.clusters.relabel_pixels, a pass over the tiles per round
        with run.stage("relabel"):
            moved = 0
            lab_path = opt.scratch / "relabelled.npy"
            _memmap(lab_path, (h, w), np.int64).flush()
            for _ in range(RELABEL_ROUNDS):
                n = sum(passes.map("relabel", s=s, alpha=alpha, per_obs=float(cost.sum()) / max(1.0, sums.n_total),
                                   labels_file=str(lab_path)))
                if n == 0:
                    break
                moved += n
                passes.base["labeler"] = LabelMap(str(lab_path), k)
                passes.base["ref"] = Reference(s, alpha)  # the first LM evaluation at the current α
                A, first, _, _, _, area = _sums(passes, k, True, True)
                passes.base["ref"] = ref  # the texture pass's fallback stays the subsample's, as in memory
                s, alpha, cost, res = _solve_specular(passes, dt, torch.log(alpha), first, A, tol=opt.tol,
                                                      max_iters=opt.max_iters, s_fixed=s_fix, beta_fixed=b_fix,
                                                      on_iter=lambda it, ev: None)
            run.log("relabel", 1, math.sqrt(float(cost.sum()) / max(1.0, sums.n_total)), 1.0, moved)
    return s, alpha, cost, area, res.status


def _texture(passes: TilePasses, run: FitRun, tiles: list, grid: tuple[int, int], s, alpha, med, with_labels: bool,
             scratch: Path) -> tuple[np.memmap, np.memmap | None]:
    """The last pass: the texture of each tile in closed form, texels never observed usefully inpainted
    from their neighbours, into ``scratch/texture.npy``. Returns that file and, with labels, the pixels'
    cluster labels (``scratch/specular_labels.npy``)."""
    h, w = grid
    raw_file = _memmap(scratch / "texture_raw.npy", (h, w, 3), np.float32)
    bad_file = _memmap(scratch / "unobserved.npy", (h, w, 3), np.bool_)
    lab_file = _memmap(scratch / "specular_labels.npy", (h, w), np.int64) if with_labels else None
    for m in (raw_file, bad_file, lab_file):
        if m is not None:
            m.flush()
    with run.stage("texture"):
        n_bad = sum(passes.map("texture", s=s, alpha=alpha, median=med, raw_file=str(scratch / "texture_raw.npy"),
                               bad_file=str(scratch / "unobserved.npy"),
                               labels_file=None if lab_file is None else str(scratch / "specular_labels.npy")))
        if n_bad:
            run.skipped.append(f"texture: {n_bad} mask pixel(s) never observed usefully (grazing, shadowed or saturated "
                               "in every shot) are inpainted from their neighbours")
        tex_file = _memmap(scratch / "texture.npy", (h, w, 3), np.float32)
        fill_tiles(raw_file, bad_file, tiles, tex_file)
    tex_file.flush()
    del raw_file, bad_file
    for f in ("texture_raw.npy", "unobserved.npy"):
        (scratch / f).unlink(missing_ok=True)
    return tex_file, lab_file


def _normals(cap: TiledCapture, tiles: list, flat: bool, dt: torch.dtype, scratch: Path) -> Tensor:
    """The result's normals (3, H, W): +z when ``flat``, else the capture's, copied tile by tile into
    ``scratch/normals.npy``."""
    h, w = cap.height, cap.width
    if flat:
        return torch.tensor([0.0, 0.0, 1.0], dtype=dt).view(3, 1, 1).expand(3, h, w)
    nrm_file = _memmap(scratch / "normals.npy", (h, w, 3), np.float32)
    for rows, cols in tiles:
        nrm_file[rows, cols] = cap.normals[:, rows, cols].permute(1, 2, 0).numpy()
    nrm_file.flush()
    return torch.from_numpy(nrm_file).permute(2, 0, 1)


def fit_tiled_material(capture_path: str | os.PathLike, *, tile: int, scheme: str = "refine", specular: str = "auto",
                       flakes: str = "auto", tol: float = 1e-6, max_iters: int = 100, robust: str | None = "auto",
                       seed: int = 0, progress: bool = False, scratch: str | Path, engine: str | None = None,
                       workers: int = 1) -> PipelineResult:
    """``fit --tile``: a tiled capture (or any capture, converted into ``scratch`` first, one
    image at a time) → :class:`~torchmetal.pipeline.PipelineResult` with the flake stage skipped.

    ``engine``, ``workers``: where the tile tasks run (:func:`fit_tiled`). Other options as
    :func:`~torchmetal.pipeline.fit_material`; the tiled fit is the refine scheme by
    least squares (robust "auto" is that when no flakes are fitted), so other values are refused.
    """
    check_tiled(FitConfig.of(scheme=scheme, robust=robust, flakes=flakes))  # what it supports: torchmetal.config
    t0 = time.perf_counter()
    scratch = Path(scratch)
    skipped = []
    path = capture_path
    if not is_tiled(capture_path):
        path = convert_capture(capture_path, scratch / "capture")
        skipped.append("tiles: the capture's images are not .npy arrays; converted to a tiled capture first")
    fit = fit_tiled(path, tile=tile, specular=specular, tol=tol, max_iters=max_iters, seed=seed, progress=progress,
                    scratch=scratch / "result", engine=engine, workers=workers)
    skipped += list(fit.skipped)
    skipped.append("flakes: not run by the tiled fit (flake detection needs whole images)")
    report = {"stage_times": {f"phong.{k}": v for k, v in fit.stage_times.items()}, "total_time": time.perf_counter() - t0,
              "skipped": skipped, "status": fit.status, "iterations": fit.iterations, "rmse": fit.rmse, "flakes": None,
              "tiled": {k: v for k, v in fit.tiled.items() if k not in ("scratch", "engine", "workers")}}
    material = fit.to_material(report_extra=report)
    result = PipelineResult(material=material, fit=fit, flakes=None, report=material.report)
    result.capture = TiledCapture(path)
    return result
