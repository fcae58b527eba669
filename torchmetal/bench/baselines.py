"""Reference implementations the benchmark measures torchmetal against.

Two baselines, both fitting the paper's model (docs/design.md §2.2)
``I_k(p)_c = E_c·[d_c(p)·max(n·l, 0) + [n·l > 0]·s_c·max(r·v, 0)^{α_c}]``:

* :func:`paper_scheme_numpy` — a plain numpy/scipy implementation of section 4.1 of the source
  paper, written the straightforward way a CPU reference would be: T_min initial approximation
  (4.1.6), then iterations of specular extraction (4.1.1), control points from r·v bins with
  averaged colours (4.1.2), ``scipy.optimize.least_squares(method="lm")`` on (s, α) per channel
  (4.1.3), texture recomputation as the average of Diffuse/(n·l) (4.1.4) and the |ΔErr| stop
  (4.1.5). No torch anywhere in the computation.
* :func:`adam_fit` — a per-pixel autograd fit of the same model with Adam (texture, s, log α),
  ~2000 full-batch steps with a cosine learning-rate schedule, the way learned-prior-free SVBRDF
  optimisers do it.

Both take any capture-like object with ``images (N,3,H,W)``, ``normals``, ``lights (N,4)``,
``intensities (N,3)``, ``cameras (N,4)`` and ``size``; ``mask`` and ``saturated`` are used when
present. Tensors or arrays are accepted.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from torchmetal.bench.np_phong import _lobe, _np, capture_arrays, np_geometry, np_render

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, DTypeLike
    from torch import Tensor

    from torchmetal.io.capture import Capture

__all__ = ["BaselineResult", "capture_arrays", "np_geometry", "np_render", "paper_scheme_numpy", "adam_fit"]

_NL_MIN = 1e-3  # observations with n·l below this are "not lit" for the baselines (1/n·l blows up)


@dataclass
class BaselineResult:
    """Fitted parameters (numpy, float64) plus timing and the per-iteration error history."""

    name: str
    texture: np.ndarray  # (3, H, W)
    s: np.ndarray  # (3,)
    alpha: np.ndarray  # (3,)
    seconds: float
    iterations: int
    history: list[float] = field(default_factory=list)
    stage_times: dict[str, float] = field(default_factory=dict)
    status: str = "converged"

    def render(self, light: ArrayLike, intensity: ArrayLike, camera: ArrayLike, normals: ArrayLike,
               size: tuple[float, float]) -> np.ndarray:
        """Render shots (B, 3, H, W) of the fitted parameters (numpy, no torch)."""
        return np_render(self.texture, self.s, self.alpha, _np(normals), _np(light), _np(intensity), _np(camera), size)


# --------------------------------------------------------------------------- the paper's scheme


def _bin_index(q: np.ndarray, n_bins: int, q_min: float) -> np.ndarray:
    """Bins of equal r·v: geometric in q = 1 − r·v on [q_min, 1) so narrow lobes keep resolution.

    Bin 0 holds q < q_min (the mirror direction), bin n_bins+1 holds r·v ≤ 0.
    """
    lq = np.log(np.maximum(q, q_min * 0.5))
    t = (lq - math.log(q_min)) / (-math.log(q_min)) * n_bins
    b = np.clip(np.floor(t).astype(np.int64) + 1, 0, n_bins)
    b = np.where(q < q_min, 0, b)
    return np.where(q >= 1.0, n_bins + 1, b)


class _Bins:
    """Control-point bins of one channel's observations (4.1.2), built once: r·v never changes."""

    def __init__(self, q_obs: np.ndarray, n_bins: int, q_min: float) -> None:
        b = _bin_index(q_obs, n_bins, q_min)
        nb = n_bins + 2
        self.count = np.bincount(b, minlength=nb)
        self.keep = self.count > 0
        self.index = b.astype(np.int16 if nb < 2**15 else np.int64)
        self.nb = nb
        q_sum = np.bincount(b, weights=q_obs, minlength=nb)
        # the paper's sets share one r·v exactly; with binning the bin's mean is that shared value
        self.q = q_sum[self.keep] / self.count[self.keep]
        member = np.full(nb, -1, np.int64)
        member[b] = np.arange(b.size)  # "from each set we choose an arbitrary point"
        self.member = member[self.keep]

    def mean(self, value: np.ndarray) -> np.ndarray:
        """Average colour c_i of every non-empty bin."""
        sums = np.bincount(self.index, weights=value, minlength=self.nb)
        return sums[self.keep] / self.count[self.keep]


def _lm_channel(rv_q: np.ndarray, c: np.ndarray, x0: np.ndarray, extra=None):
    """least_squares LM on (s, log α) for one channel. ``extra`` adds the init-term features."""
    from scipy.optimize import least_squares

    lg = np.log1p(-np.minimum(rv_q, 1.0 - 1e-16))  # log(r·v); r·v ≤ 0 gives lobe 0 below
    off = rv_q >= 1.0

    def lobe(beta):
        return np.where(off, 0.0, np.exp(np.exp(beta) * lg))

    if extra is None:
        def res(x):
            return x[0] * lobe(x[1]) - c

        def jac(x):
            lb = lobe(x[1])
            return np.stack([lb, x[0] * lb * np.exp(x[1]) * lg], 1)
    else:
        lg_star, off_star, nl_star, nl = extra  # X(p) = s·(r·v*)^α / (n·l*), times n·l of this shot

        def lobe_star(beta):
            return np.where(off_star, 0.0, np.exp(np.exp(beta) * lg_star))

        def res(x):
            return x[0] * (lobe(x[1]) - lobe_star(x[1]) / nl_star * nl) - c

        def jac(x):
            a = np.exp(x[1])
            lb, ls = lobe(x[1]), lobe_star(x[1])
            ds = lb - ls / nl_star * nl
            db = x[0] * a * (lb * lg - ls * np.where(off_star, 0.0, lg_star) / nl_star * nl)
            return np.stack([ds, db], 1)

    if c.size < 2:
        return np.array([0.0, x0[1]]), 0
    sol = least_squares(res, x0, jac=jac, method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=200)
    x = sol.x
    if not np.all(np.isfinite(x)):
        x = np.asarray(x0, np.float64)
    return x, int(sol.nfev)


def paper_scheme_numpy(
    capture: Capture,
    *,
    tol: float = 1e-6,
    max_iters: int = 100,
    n_bins: int = 256,
    q_min: float = 1e-6,
    alpha0: float = 20.0,
    dtype: DTypeLike = np.float32,
) -> BaselineResult:
    """The source paper's section 4.1, in plain numpy + ``scipy.optimize.least_squares``.

    Written as a competent CPU reference, not a strawman: float32 storage, float64 sums, r·v
    bins built once, per-shot loops that keep temporaries at one image, LM only on the
    control points.

    Args:
        capture: capture-like object (see module docstring).
        tol: stop when |Err_{i−1} − Err_i| ≤ tol·Err_{i−1} (the paper's ε, made relative).
        max_iters: iteration cap.
        n_bins: number of r·v bins for the control points (4.1.2).
        q_min: smallest 1 − r·v bin edge; bins are geometric in 1 − r·v.
        alpha0: starting exponent for the LM of the initial approximation.
        dtype: storage dtype of the per-observation arrays (sums are float64).

    Returns:
        :class:`BaselineResult` with ``stage_times`` for geometry, init, specular, texture, error.
    """
    t_start = time.perf_counter()
    laps = _Laps()
    t = time.perf_counter()
    a = _paper_arrays(capture, dtype, n_bins, q_min)
    t = laps("geometry", t)
    texture, s, beta, nfev = _initial_approximation(a, alpha0, dtype)
    t = laps("init", t)
    history: list[float] = []
    err_prev = math.inf
    iters = 0
    status = "max_iters"
    for it in range(max_iters):
        iters = it + 1
        # 4.1.1 specular = image − diffuse(T^{i−1});  4.1.2 control points;  4.1.3 LM per channel
        nfev += _specular_step(a, texture, s, beta)
        t = laps("specular", t)
        # 4.1.4 texture = mean_k (image − specular) / (n·l) over the shots that see the pixel lit
        texture = _texture_step(a, s, beta, dtype)
        t = laps("texture", t)
        # 4.1.5 Err_i = Σ (Image − Image')², stop on |ΔErr| ≤ ε
        err = _error(a, texture, s, beta, dtype)
        history.append(err)
        t = laps("error", t)
        if abs(err_prev - err) <= tol * max(err_prev if math.isfinite(err_prev) else err, 1e-300):
            status = "converged"
            break
        err_prev = err
    return BaselineResult(
        name="paper-numpy", texture=texture.astype(np.float64), s=s.copy(), alpha=np.exp(beta),
        seconds=time.perf_counter() - t_start, iterations=iters, history=history,
        stage_times={**laps.times, "lm_evaluations": float(nfev)}, status=status,
    )


class _Laps:
    """Stage times: ``laps(name, t0)`` adds the time since t0 to the stage and returns now."""

    def __init__(self) -> None:
        self.times: dict[str, float] = {}

    def __call__(self, name: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.times[name] = self.times.get(name, 0.0) + (t1 - t0)
        return t1


@dataclass
class _PaperArrays:
    """The per-observation arrays of :func:`paper_scheme_numpy`, built once (r·v never changes)."""

    images: np.ndarray  # (N, 3, H, W), 0 where not valid
    valid: np.ndarray  # (N, 3, H, W) bool
    nl: np.ndarray  # (N, 1, H, W) n·l
    q: np.ndarray  # (N, 1, H, W) 1 − r·v
    e: np.ndarray  # (N, 3, H, W) irradiance
    lit: np.ndarray  # (N, 1, H, W) n·l > _NL_MIN
    obs: np.ndarray  # (N, 3, H, W) valid and lit
    y: np.ndarray  # reflectance units: I / E
    inv_nl: np.ndarray  # 1/(n·l), 0 where unlit
    log_rv: np.ndarray  # log(r·v) where r·v > 0
    rv_pos: np.ndarray  # r·v > 0
    nl_pos: np.ndarray  # max(n·l, 0)
    n_obs: np.ndarray  # (3, H, W) observations per texel, at least 1
    bins: list[_Bins]  # per channel

    @property
    def n_shots(self) -> int:
        return self.images.shape[0]


def _paper_arrays(capture: Capture, dtype: DTypeLike, n_bins: int, q_min: float) -> _PaperArrays:
    a = capture_arrays(capture, dtype)
    images, valid = a["images"], a["valid"]
    nl, q, e = np_geometry(a["normals"], a["lights"], a["intensities"], a["cameras"], a["size"], dtype=dtype)
    lit = nl > _NL_MIN  # (N,1,H,W)
    obs = valid & lit  # (N,3,H,W)
    y = images / np.maximum(e, np.finfo(dtype).tiny)  # reflectance units: I / E
    inv_nl = np.where(lit, 1.0 / np.where(lit, nl, 1.0), 0.0).astype(dtype)  # 1/(n·l), 0 where unlit
    log_rv = np.log1p(-np.where(q < 1.0, q, 0.5)).astype(dtype)  # log(r·v) where r·v > 0
    rv_pos = q < 1.0
    nl_pos = np.maximum(nl, 0.0)
    n_obs = np.maximum(obs.sum(0), 1)  # (3,H,W)
    same_obs = bool(np.all(obs == obs[:, :1]))
    bins = []
    for c in range(3):
        if c > 0 and same_obs:
            bins.append(bins[0])
        else:
            bins.append(_Bins(q[:, 0][obs[:, c]].astype(np.float64), n_bins, q_min))
    return _PaperArrays(images=images, valid=valid, nl=nl, q=q, e=e, lit=lit, obs=obs, y=y, inv_nl=inv_nl, log_rv=log_rv,
                        rv_pos=rv_pos, nl_pos=nl_pos, n_obs=n_obs, bins=bins)


def _initial_approximation(a: _PaperArrays, alpha0: float, dtype: DTypeLike) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """4.1.6: T_min = min_k I_k / (n·l)_k, then s0, α0 fitted to what T_min leaves. Returns (texture, s, β,
    LM evaluations)."""
    images, obs, y, q, nl = a.images, a.obs, a.y, a.q, a.nl
    ratio = np.where(obs, y * a.inv_nl, np.inf)
    kstar = np.argmin(ratio, axis=0)  # (3,H,W)
    t_min = np.take_along_axis(ratio, kstar[None], 0)[0]
    del ratio
    t_min = np.where(np.isfinite(t_min), t_min, 0.0).astype(dtype)
    s = np.zeros(3)
    beta = np.full(3, math.log(alpha0))
    nfev = 0
    q_star = np.empty((3,) + images.shape[2:], dtype)
    nl_star = np.empty_like(q_star)
    for c in range(3):
        q_star[c] = np.take_along_axis(q[:, 0], kstar[c][None], 0)[0]
        nl_star[c] = np.take_along_axis(nl[:, 0], kstar[c][None], 0)[0]
        oc = obs[:, c]
        resid = (y[:, c] - t_min[c][None] * nl[:, 0])[oc].astype(np.float64)
        bc = a.bins[c]
        mean = bc.mean(resid)
        m = bc.member  # one arbitrary observation per bin carries the geometry of X(p)
        qs = np.broadcast_to(q_star[c][None], oc.shape)[oc][m].astype(np.float64)
        ns = np.broadcast_to(nl_star[c][None], oc.shape)[oc][m].astype(np.float64)
        nlc = nl[:, 0][oc][m].astype(np.float64)
        qm = q[:, 0][oc][m].astype(np.float64)
        x0 = np.array([max(float(np.max(mean)) if mean.size else 0.0, 1e-6), beta[c]])
        extra = (np.log1p(-np.minimum(qs, 1.0 - 1e-16)), qs >= 1.0, np.maximum(ns, _NL_MIN), nlc)
        x, k = _lm_channel(qm, mean, x0, extra)
        nfev += k
        s[c], beta[c] = max(x[0], 0.0), x[1]
        del resid
    lobe_star = _lobe(q_star.astype(np.float64), np.exp(beta)[:, None, None])
    texture = (t_min - s[:, None, None] * lobe_star / np.maximum(nl_star, _NL_MIN)).astype(dtype)
    return texture, s, beta, nfev


def _spec_shot(a: _PaperArrays, s: np.ndarray, beta: np.ndarray, k: int, dtype: DTypeLike) -> np.ndarray:
    """s·max(r·v, 0)^α for shot k where n·l > 0, (3, H, W)."""
    lobe = np.exp(np.exp(beta).astype(dtype).reshape(3, 1, 1) * a.log_rv[k])
    return np.where(a.lit[k] & a.rv_pos[k], s.astype(dtype).reshape(3, 1, 1) * lobe, 0.0).astype(dtype, copy=False)


def _specular_step(a: _PaperArrays, texture: np.ndarray, s: np.ndarray, beta: np.ndarray) -> int:
    """4.1.1–4.1.3 per channel: the specular left by the texture, its control points, LM on (s, log α); ``s`` and
    ``beta`` are updated in place. Returns the LM evaluations."""
    nfev = 0
    for c in range(3):
        oc = a.obs[:, c]
        spec_obs = (a.y[:, c] - texture[c][None] * a.nl[:, 0])[oc]
        mean = a.bins[c].mean(spec_obs.astype(np.float64))
        x0 = np.array([max(s[c], 1e-6), beta[c]])
        x, k = _lm_channel(a.bins[c].q, mean, x0)
        nfev += k
        s[c], beta[c] = max(x[0], 0.0), x[1]
    return nfev


def _texture_step(a: _PaperArrays, s: np.ndarray, beta: np.ndarray, dtype: DTypeLike) -> np.ndarray:
    """4.1.4: mean over the shots that see a texel lit of (image − specular) / (n·l)."""
    acc = np.zeros((3,) + a.images.shape[2:], np.float64)
    for k in range(a.n_shots):
        acc += np.where(a.obs[k], (a.y[k] - _spec_shot(a, s, beta, k, dtype)) * a.inv_nl[k], 0.0)
    return (acc / a.n_obs).astype(dtype)


def _error(a: _PaperArrays, texture: np.ndarray, s: np.ndarray, beta: np.ndarray, dtype: DTypeLike) -> float:
    """4.1.5: Err = Σ (Image − Image')² over valid observations."""
    err = 0.0
    for k in range(a.n_shots):
        d = a.images[k] - a.e[k] * (texture * a.nl_pos[k] + _spec_shot(a, s, beta, k, dtype))
        err += float(np.sum(np.where(a.valid[k], d * d, 0.0), dtype=np.float64))
    return err


# --------------------------------------------------------------------------- Adam baseline


def adam_fit(
    capture: Capture,
    *,
    steps: int = 2000,
    lr: float = 0.05,
    lr_final: float = 5e-4,
    s0: float = 0.1,
    alpha0: float = 10.0,
    time_budget: float | None = None,
    log_every: int = 50,
) -> BaselineResult:
    """Per-pixel autograd fit of the Phong model with Adam (no learned prior).

    Parameters: texture (3, H, W), s (3,), log α (3,). The texture is optimised in units of its
    mean initial value (so one learning rate suits all parameters); s starts at ``s0``·(image
    scale), α at ``alpha0``. Full-batch MSE on the valid observations divided by irradiance,
    cosine-decayed learning rate from ``lr`` to ``lr_final``.

    Args:
        steps: Adam steps (≈ 2000 as in learned-prior-free SVBRDF optimisers).
        time_budget: optional wall-clock cap in seconds; the result's status says "time_budget".
    """
    import torch

    t_start = time.perf_counter()
    p = _adam_problem(capture)
    u = torch.nn.Parameter(p.t_init / p.scale)
    s_par = torch.nn.Parameter(torch.full((3,), s0 * float(p.y[p.w > 0].max()) if bool((p.w > 0).any()) else s0))
    log_a = torch.nn.Parameter(torch.full((3,), math.log(alpha0)))
    opt = torch.optim.Adam([u, s_par, log_a], lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps, 1), eta_min=lr_final)
    y_norm = float((p.y * p.w).square().sum() / p.wsum) or 1.0
    history: list[float] = []
    status = "max_iters"
    done = 0
    for step in range(steps):
        opt.zero_grad(set_to_none=True)
        loss = ((_adam_model(p, u, s_par, log_a) - p.y).square() * p.w).sum() / p.wsum / y_norm
        loss.backward()
        opt.step()
        sched.step()
        with torch.no_grad():
            s_par.clamp_(min=0.0)
            log_a.clamp_(min=-5.0, max=10.0)
        done = step + 1
        if step % log_every == 0 or step == steps - 1:
            history.append(float(loss.detach()) * y_norm)
        if time_budget is not None and time.perf_counter() - t_start > time_budget:
            status = "time_budget"
            break
    if status != "time_budget":
        status = "converged" if done == steps else status
    return BaselineResult(
        name="adam", texture=(u.detach() * p.scale).double().numpy(), s=s_par.detach().double().numpy(),
        alpha=log_a.detach().exp().double().numpy(), seconds=time.perf_counter() - t_start,
        iterations=done, history=history, stage_times={"adam": time.perf_counter() - t_start}, status=status,
    )


@dataclass
class _AdamProblem:
    """What :func:`adam_fit` precomputes: the geometry is fixed during the fit."""

    nl: Tensor  # (N, 1, H, W) max(n·l, 0)
    y: Tensor  # (N, 3, H, W) I / E
    w: Tensor  # (N, 3, H, W) 0/1: valid and lit
    wsum: Tensor  # Σ w, at least 1
    t_init: Tensor  # (3, H, W) initial texture
    scale: float  # the texture's unit: its mean initial value
    spec_on: Tensor  # (N, 1, H, W) 0/1: the lobe's support
    log_rv: Tensor  # (N, 1, H, W) log(r·v) where r·v > 0


def _adam_problem(capture: Capture) -> _AdamProblem:
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.geometry import shading_geometry

    a = capture_arrays(capture, np.float32)
    images = torch.from_numpy(a["images"])
    valid = torch.from_numpy(a["valid"])
    normals = torch.from_numpy(a["normals"].astype(np.float32))
    geom = shading_geometry(
        normals, torch.from_numpy(a["lights"]).float(), torch.from_numpy(a["intensities"]).float(),
        torch.from_numpy(a["cameras"]).float(), a["size"],
    )
    lit = geom.n_dot_l > 0
    nl = geom.n_dot_l.clamp_min(0.0)
    y = images / geom.irradiance.clamp_min(torch.finfo(torch.float32).tiny)
    w = (valid & lit).float()
    wsum = w.sum().clamp_min(1.0)
    # initial texture: per-pixel mean of I/(E n·l) over well-lit observations, a common init
    good = (w > 0) & (geom.n_dot_l > 0.2)
    t_init = torch.where(good, y / geom.n_dot_l.clamp_min(0.2), torch.zeros_like(y)).sum(0) / good.sum(0).clamp_min(1)
    scale = float(t_init.mean().clamp_min(1e-8))
    # geometry is fixed during the fit: precompute log(r·v) and the lobe's support once
    q = geom.spec_q
    spec_on = (lit & (q < 1.0)).float()
    log_rv = torch.log1p(-torch.where(q < 1.0, q, torch.full_like(q, 0.5)))
    return _AdamProblem(nl=nl, y=y, w=w, wsum=wsum, t_init=t_init, scale=scale, spec_on=spec_on, log_rv=log_rv)


def _adam_model(p: _AdamProblem, u: Tensor, s_par: Tensor, log_a: Tensor) -> Tensor:
    """The model's I / E: texture (in units of ``p.scale``)·n·l + s·max(r·v, 0)^α."""
    import torch

    lobe = torch.exp(log_a.exp().reshape(1, 3, 1, 1) * p.log_rv) * p.spec_on
    return (u * p.scale) * p.nl + s_par.reshape(1, 3, 1, 1) * lobe
