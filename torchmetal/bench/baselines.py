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

import numpy as np

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

    def render(self, light, intensity, camera, normals, size) -> np.ndarray:
        """Render shots (B, 3, H, W) of the fitted parameters (numpy, no torch)."""
        return np_render(self.texture, self.s, self.alpha, _np(normals), _np(light), _np(intensity), _np(camera), size)


# --------------------------------------------------------------------------- input handling


def _np(x, dtype=None) -> np.ndarray | None:
    """Array from a numpy array or a torch tensor (duck-typed, so this module never imports torch)."""
    if x is None:
        return None
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    a = np.asarray(x)
    return a.astype(dtype, copy=False) if dtype is not None else a


def _normals_chw(normals, h: int, w: int) -> np.ndarray:
    if normals is None:
        n = np.zeros((3, h, w), np.float64)
        n[2] = 1.0
        return n
    n = _np(normals, np.float64)
    if n.ndim == 4:
        n = n[0]
    if n.shape == (h, w, 3):
        n = np.moveaxis(n, -1, 0)
    if n.shape != (3, h, w):
        raise ValueError(f"normals: expected shape (3, {h}, {w}), found {n.shape}")
    return n


def capture_arrays(capture, dtype=np.float32) -> dict:
    """numpy view of a capture: images, normals, lights, intensities, cameras, size, valid.

    ``valid`` (N, 3, H, W) bool is True for observations that are finite, inside the mask and not
    saturated.
    """
    images = _np(capture.images, dtype)
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"images: expected shape (N, 3, H, W), found {images.shape}")
    n_shots, _, h, w = images.shape
    valid = np.isfinite(images)
    mask = _np(getattr(capture, "mask", None))
    if mask is not None:
        valid &= np.asarray(mask, bool).reshape(1, 1, h, w)
    sat = _np(getattr(capture, "saturated", None))
    if sat is not None:
        sat = np.asarray(sat, bool)
        if sat.ndim == 3:
            sat = sat[:, None]
        valid &= ~np.broadcast_to(sat, images.shape)
    size = capture.size
    return {
        "images": np.where(valid, images, 0).astype(dtype, copy=False),
        "normals": _normals_chw(getattr(capture, "normals", None), h, w),
        "lights": _np(capture.lights, np.float64).reshape(n_shots, 4),
        "intensities": _np(capture.intensities, np.float64).reshape(n_shots, 3),
        "cameras": _np(capture.cameras, np.float64).reshape(n_shots, 4),
        "size": (float(size[0]), float(size[1])),
        "valid": valid,
    }


# --------------------------------------------------------------------------- numpy geometry


def _surface_points(h: int, w: int, size) -> np.ndarray:
    y = (0.5 - (np.arange(h) + 0.5) / h) * size[1]
    x = ((np.arange(w) + 0.5) / w - 0.5) * size[0]
    yy, xx = np.meshgrid(y, x, indexing="ij")
    return np.stack([xx, yy, np.zeros_like(xx)])


def _direction_to(points: np.ndarray, target: np.ndarray):
    """Unit directions (B,3,H,W) from points to homogeneous targets, and squared distance (B,1,H,W)."""
    xyz = target[:, :3, None, None]
    wgt = target[:, 3:4, None, None]
    d = xyz - wgt * points[None]
    d2 = np.sum(d * d, axis=1, keepdims=True)
    unit = d / np.sqrt(np.maximum(d2, 1e-24))
    dist2 = np.where(wgt > 0.5, d2, 1.0)
    return unit, dist2


def np_geometry(normals: np.ndarray, lights: np.ndarray, intensities: np.ndarray, cameras: np.ndarray, size, dtype=np.float32):
    """n·l, q = 1 − r·v (from |r − v|²/2) and irradiance E, each (B, 1|3, H, W), in ``dtype``."""
    _, h, w = normals.shape
    pts = _surface_points(h, w, size)
    n = normals[None]
    out_nl, out_q, out_e = [], [], []
    for k in range(lights.shape[0]):  # one shot at a time keeps float64 temporaries small
        l, dist2 = _direction_to(pts, lights[k : k + 1])
        v, _ = _direction_to(pts, cameras[k : k + 1])
        nl = np.sum(n * l, axis=1, keepdims=True)
        r = 2.0 * nl * n - l
        rv = r - v
        out_nl.append(nl.astype(dtype))
        out_q.append((0.5 * np.sum(rv * rv, axis=1, keepdims=True)).astype(dtype))
        out_e.append((intensities[k][None, :, None, None] / dist2).astype(dtype))
    return np.concatenate(out_nl), np.concatenate(out_q), np.concatenate(out_e)


def _lobe(q: np.ndarray, alpha) -> np.ndarray:
    """max(r·v, 0)^α = exp(α·log1p(−q)) for q < 1, else 0; α broadcast per channel."""
    inside = q < 1.0
    lg = np.log1p(-np.where(inside, q, 0.5))
    return np.where(inside, np.exp(np.asarray(alpha) * lg), 0.0)


def np_render(texture, s, alpha, normals, light, intensity, camera, size) -> np.ndarray:
    """numpy Phong render of B shots (docs/design.md §2.2), (B, 3, H, W) float64."""
    nl, q, e = np_geometry(np.asarray(normals, np.float64), np.asarray(light, np.float64).reshape(-1, 4),
                           np.asarray(intensity, np.float64).reshape(-1, 3), np.asarray(camera, np.float64).reshape(-1, 4),
                           size, dtype=np.float64)
    s3 = np.asarray(s, np.float64).reshape(1, 3, 1, 1)
    a3 = np.asarray(alpha, np.float64).reshape(1, 3, 1, 1)
    spec = np.where(nl > 0, s3 * _lobe(q, a3), 0.0)
    return e * (np.asarray(texture, np.float64)[None] * np.maximum(nl, 0.0) + spec)


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
    capture,
    *,
    tol: float = 1e-6,
    max_iters: int = 100,
    n_bins: int = 256,
    q_min: float = 1e-6,
    alpha0: float = 20.0,
    dtype=np.float32,
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
    times: dict[str, float] = {}

    def lap(name: str, t0: float) -> float:
        t1 = time.perf_counter()
        times[name] = times.get(name, 0.0) + (t1 - t0)
        return t1

    t = time.perf_counter()
    a = capture_arrays(capture, dtype)
    images, valid = a["images"], a["valid"]
    n_shots = images.shape[0]
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
    t = lap("geometry", t)

    # 4.1.6 initial approximation: T_min = min_k I_k / (n·l)_k, then fit s0, α0 to what T_min leaves.
    ratio = np.where(obs, y * inv_nl, np.inf)
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
        bc = bins[c]
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
    del lobe_star, q_star, nl_star, t_min, kstar
    t = lap("init", t)

    def spec_shot(k: int) -> np.ndarray:
        """s·max(r·v, 0)^α for shot k where n·l > 0, (3, H, W)."""
        lobe = np.exp(np.exp(beta).astype(dtype).reshape(3, 1, 1) * log_rv[k])
        return np.where(lit[k] & rv_pos[k], s.astype(dtype).reshape(3, 1, 1) * lobe, 0.0).astype(dtype, copy=False)

    history: list[float] = []
    err_prev = math.inf
    iters = 0
    status = "max_iters"
    for it in range(max_iters):
        iters = it + 1
        # 4.1.1 specular = image − diffuse(T^{i−1});  4.1.2 control points;  4.1.3 LM per channel
        for c in range(3):
            oc = obs[:, c]
            spec_obs = (y[:, c] - texture[c][None] * nl[:, 0])[oc]
            mean = bins[c].mean(spec_obs.astype(np.float64))
            x0 = np.array([max(s[c], 1e-6), beta[c]])
            x, k = _lm_channel(bins[c].q, mean, x0)
            nfev += k
            s[c], beta[c] = max(x[0], 0.0), x[1]
        t = lap("specular", t)
        # 4.1.4 texture = mean_k (image − specular) / (n·l) over the shots that see the pixel lit
        acc = np.zeros((3,) + images.shape[2:], np.float64)
        for k in range(n_shots):
            acc += np.where(obs[k], (y[k] - spec_shot(k)) * inv_nl[k], 0.0)
        texture = (acc / n_obs).astype(dtype)
        t = lap("texture", t)
        # 4.1.5 Err_i = Σ (Image − Image')², stop on |ΔErr| ≤ ε
        err = 0.0
        for k in range(n_shots):
            d = images[k] - e[k] * (texture * nl_pos[k] + spec_shot(k))
            err += float(np.sum(np.where(valid[k], d * d, 0.0), dtype=np.float64))
        history.append(err)
        t = lap("error", t)
        if abs(err_prev - err) <= tol * max(err_prev if math.isfinite(err_prev) else err, 1e-300):
            status = "converged"
            break
        err_prev = err
    return BaselineResult(
        name="paper-numpy", texture=texture.astype(np.float64), s=s.copy(), alpha=np.exp(beta),
        seconds=time.perf_counter() - t_start, iterations=iters, history=history,
        stage_times={**times, "lm_evaluations": float(nfev)}, status=status,
    )


# --------------------------------------------------------------------------- Adam baseline


def adam_fit(
    capture,
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

    # on use: loads torch (this module imports numpy only)
    from torchmetal.geometry import shading_geometry

    t_start = time.perf_counter()
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
    u = torch.nn.Parameter(t_init / scale)
    s_par = torch.nn.Parameter(torch.full((3,), s0 * float(y[w > 0].max()) if bool((w > 0).any()) else s0))
    log_a = torch.nn.Parameter(torch.full((3,), math.log(alpha0)))
    opt = torch.optim.Adam([u, s_par, log_a], lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps, 1), eta_min=lr_final)
    y_norm = float((y * w).square().sum() / wsum) or 1.0
    # geometry is fixed during the fit: precompute log(r·v) and the lobe's support once
    q = geom.spec_q
    spec_on = (lit & (q < 1.0)).float()
    log_rv = torch.log1p(-torch.where(q < 1.0, q, torch.full_like(q, 0.5)))
    del geom, images, valid, good, q

    def model_y():
        lobe = torch.exp(log_a.exp().reshape(1, 3, 1, 1) * log_rv) * spec_on
        return (u * scale) * nl + s_par.reshape(1, 3, 1, 1) * lobe

    history: list[float] = []
    status = "max_iters"
    done = 0
    for step in range(steps):
        opt.zero_grad(set_to_none=True)
        loss = ((model_y() - y).square() * w).sum() / wsum / y_norm
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
        name="adam", texture=(u.detach() * scale).double().numpy(), s=s_par.detach().double().numpy(),
        alpha=log_a.detach().exp().double().numpy(), seconds=time.perf_counter() - t_start,
        iterations=done, history=history, stage_times={"adam": time.perf_counter() - t_start}, status=status,
    )
