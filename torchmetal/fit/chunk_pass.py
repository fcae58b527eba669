"""One chunk of the observation pass: what :func:`~torchmetal.fit.problem.build_observations` does per chunk.

:class:`ObservationPass` holds a pass's inputs on the pixel grid and the per-pixel maps it fills;
:func:`observe_chunk` fills them for one chunk of pixels: validity, labels and T_min, the weights at the
reference specular (IRLS or outlier masks), the diffuse-only solution and its residual energy, the
fallback texture, the chunk's largest log-lobe and the variable-projection stats (see the module
docstring of :mod:`torchmetal.fit.problem` for what each map is).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import torch
from torch import Tensor

from torchmetal.fit.grid_terms import base_validity
from torchmetal.fit.lobes import LOG_OFF, lobe_terms
from torchmetal.fit.projected_sums import chunk_stats, reduce_stats

if TYPE_CHECKING:
    from torchmetal.fit.grid_terms import GridSource
    from torchmetal.fit.problem import Reference, Weighting


def weighted(x: Tensor, w: Tensor) -> Tensor:
    """w·x (float weights; a bool mask is converted once)."""
    return x * (as_float(w, x.dtype) if w.dtype == torch.bool else w)


def as_float(mask: Tensor, dtype: torch.dtype) -> Tensor:
    """bool → 0/1 float through a free uint8 view (bool → float directly is several times slower)."""
    return mask.view(torch.uint8).to(dtype)


def tmin_chunk(y: Tensor, a: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """T_min = min_k y/a over weighted observations with a > 0 (4.1.6); 0 where none.

    Returns (T_min (3, c), argmin shot (3, c) int64).
    """
    ok = (w > 0) & (a > 0)
    ratio = torch.where(ok, y / torch.where(ok, a, torch.ones_like(a)), torch.full_like(y, math.inf))
    t, k = ratio.min(0)
    return torch.where(torch.isfinite(t), t, torch.zeros_like(t)), k


def _irls_chunk(target: Tensor, a: Tensor, base: Tensor, weighting: Weighting, y: Tensor | None = None) -> Tensor:
    """Per-pixel IRLS of the texture against ``target`` = y − specular; float weights (n, 3, c).

    ``base`` (n, 3, c) 0/1 float. Starts from the median over shots of target/a (one glint cannot
    drag the start), and never rejects every observation of a pixel. With a noise model
    (``weighting.variance``) the weights carry :meth:`Weighting.noise_weight` of the model value
    a·d + (``y`` − ``target``), the specular term (a·d alone when ``y`` is None).
    """
    dt = a.dtype
    zero = torch.zeros((), dtype=dt, device=a.device)
    ok = base > 0
    d = torch.nanmedian(torch.where(ok, target / torch.where(ok, a, torch.ones_like(a)), torch.full_like(a, math.nan)), 0).values
    d = torch.where(torch.isnan(d), zero, d)
    w = base
    sigma = weighting.sigma.to(dt).view(1, 3, 1)
    rounds = max(1, weighting.rounds if weighting.robust is not None else min(weighting.rounds, 2))
    for i in range(rounds):
        if i > 0:
            wa = w * a
            den = (wa * a).sum(0)
            okd = den > 0
            d = torch.where(okd, (wa * target).sum(0) / torch.where(okd, den, torch.ones_like(den)), d)
        res = target - a * d
        if weighting.robust is not None:
            w = base * weighting(res)
        elif weighting.outlier_k is not None:
            w = base * as_float(res.abs() <= weighting.outlier_k * sigma, dt)
        else:
            w = base
        if weighting.variance is not None:
            pred = a * d if y is None else torch.addcmul(y - target, a, d)
            w = w * weighting.noise_weight(pred)
    lost = (w.sum(0) == 0) & (base.sum(0) > 0)
    if bool(lost.any()):
        w = torch.where(lost.unsqueeze(0), base, w)
    return w


@dataclass
class ObservationPass:
    """A pass over the pixel grid of :func:`~torchmetal.fit.problem.build_observations`: its inputs (top)
    and the maps it fills (bottom; None when not asked for). ``rows``, ``cols``: the grid's full-resolution
    slices; ``width``: the grid's width; ``ref``: the reference in the working dtype."""

    y: Tensor  # (N, 3, P)
    inten: Tensor  # (N, 3, 1)
    inten_pos: Tensor  # (N, 3, 1) bool
    mask: Tensor | None  # (1, 1, P) bool, None when every pixel is inside
    sat: Tensor | None  # (N, 3, P) bool, None when nothing is clipped
    rows: slice
    cols: slice
    width: int
    dt: torch.dtype
    zero: Tensor
    ref: Reference | None
    ref_k: int
    weighting: Weighting | None
    weighs: bool  # per-observation weights stored (robust or noise)
    labeler: Callable[[Tensor, Tensor], Tensor] | None
    want_tmin: bool
    lobe: str
    valid: Tensor | None  # (N, 3, P) uint8
    weight: Tensor | None  # (N, 3, P) wstore
    wstore: torch.dtype
    saa: Tensor
    d0: Tensor
    A: Tensor
    cnt: Tensor
    lmax: Tensor  # (N, n_chunks)
    labels: Tensor | None
    tmin: Tensor | None
    stats_acc: Tensor | None
    eb: Tensor | None
    fb: Tensor | None = None  # (3, P), allocated at the first pixel without a valid observation
    source: GridSource | None = None
    g: Tensor | None = None
    u: Tensor | None = None
    L: Tensor | None = None
    geo: Tensor | None = None


def _chunk_geometry(ps: ObservationPass, p0: int, p1: int) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor]:
    """(g, u, L, geo, base validity) of pixels [p0, p1): recomputed when streamed, else the stored terms."""
    if ps.source is not None:
        return ps.source.terms(p0, p1)
    sl = slice(p0, p1)
    g, u, L = ps.g[:, :, sl], ps.u[:, :, sl], ps.L[:, :, sl]
    geo = None if ps.geo is None else ps.geo[:, :, sl]
    base_b = base_validity(g, None if ps.mask is None else ps.mask[:, :, sl], ps.inten_pos,
                           None if ps.sat is None else ps.sat[:, :, sl])
    return g, u, L, geo, base_b


def _chunk_labels(ps: ObservationPass, yc: Tensor, a: Tensor, base: Tensor, p0: int, p1: int) -> Tensor | None:
    """T_min of the chunk (stored when asked for) and the labeler's labels of its pixels (stored; None without one)."""
    t_c = tmin_chunk(yc, a, base)[0] if (ps.want_tmin or ps.labeler is not None) else None
    lab = None
    if ps.labeler is not None:
        flat = torch.arange(p0, p1, device=yc.device)
        rows, cols, w = ps.rows, ps.cols, ps.width
        lab = ps.labeler(t_c, torch.stack([rows.start + (flat // w) * rows.step, cols.start + (flat % w) * cols.step]).to(ps.dt))
        ps.labels[p0:p1] = lab
    if ps.tmin is not None:
        ps.tmin[:, p0:p1] = t_c
    return lab


def _outlier_weights(ps: ObservationPass, target: Tensor, a: Tensor, base: Tensor, wa: Tensor, s_aa: Tensor) -> Tensor:
    """Outlier masks of a least-squares pass: IRLS only where something exceeds k·σ (else ``base`` itself)."""
    weighting = ps.weighting
    okd = s_aa > 0
    d_ref = torch.where(okd, (wa * target).sum(0) / torch.where(okd, s_aa, torch.ones_like(s_aa)), ps.zero)
    sig = (weighting.outlier_k * weighting.sigma.to(ps.dt)).view(1, 3, 1)
    exceed = ((target - a * d_ref).abs() * base) > sig
    hit = exceed.any(0).any(0).nonzero().squeeze(1)
    wts = base
    if hit.numel():
        wts = base.clone()
        wts[:, :, hit] = _irls_chunk(target[:, :, hit], a[:, :, hit], base[:, :, hit], weighting)
    return wts


def _chunk_weights(ps: ObservationPass, sl: slice, yc: Tensor, a: Tensor, base: Tensor, s_c: Tensor | None,
                   b: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """The chunk's weights at the reference (``base`` itself without weighting), w·a and Σ w·a²."""
    wts = base
    wa = a * wts
    s_aa = (wa * a).sum(0)
    weighting = ps.weighting
    if weighting is not None and b is not None:
        target = torch.addcmul(yc, s_c.unsqueeze(0), b, value=-1.0)  # y − s·b
        if ps.weighs:
            wts = _irls_chunk(target, a, base, weighting, yc)
            ps.weight[:, :, sl] = wts.to(ps.wstore)
            wts = ps.weight[:, :, sl].to(ps.dt)  # the stored (rounded) weights define the cost
        elif weighting.outlier_k is not None:  # a least-squares pass; IRLS only where something exceeds k·σ
            wts = _outlier_weights(ps, target, a, base, wa, s_aa)
        if wts is not base:
            wa = a * wts
            s_aa = (wa * a).sum(0)
    return wts, wa, s_aa


def _chunk_fallback(ps: ObservationPass, sl: slice, yc: Tensor, a: Tensor, s_c: Tensor | None, b: Tensor | None) -> None:
    """Texture where no observation is valid: all lit ones, saturated included."""
    zero = ps.zero
    la = torch.where(a > 0, a, zero)
    den = (la * a).sum(0)
    tgt = yc if b is None else torch.addcmul(yc, s_c.unsqueeze(0), b, value=-1.0)
    if ps.fb is None:
        ps.fb = torch.zeros(3, ps.y.shape[-1], dtype=ps.dt, device=yc.device)
    ps.fb[:, sl] = torch.where(den > 0, (la * tgt).sum(0) / torch.where(den > 0, den, torch.ones_like(den)), zero)


def observe_chunk(ps: ObservationPass, j: int, p0: int, p1: int) -> None:
    """Fill the pass's maps for chunk ``j``, pixels [p0, p1)."""
    sl = slice(p0, p1)
    g, u, L, geo, base_b = _chunk_geometry(ps, p0, p1)
    yc = ps.y[:, :, sl].to(ps.dt)
    a = ps.inten * g
    base = as_float(base_b, ps.dt)
    lab = _chunk_labels(ps, yc, a, base, p0, p1)
    b = t = s_c = None
    if ps.ref is not None:
        s_c, al_c = ps.ref.maps(lab, p1 - p0)
        _, b, t = lobe_terms(g, u, L, ps.inten, al_c.unsqueeze(0), geo, ps.lobe)
    wts, wa, s_aa = _chunk_weights(ps, sl, yc, a, base, s_c, b)
    if ps.valid is not None:
        ps.valid[:, :, sl] = (base_b if wts is base else wts > 0).view(torch.uint8)
    ok = s_aa > 0
    isaa_c = torch.where(ok, 1.0 / torch.where(ok, s_aa, torch.ones_like(s_aa)), ps.zero)
    dd = (wa * yc).sum(0) * isaa_c
    r0 = torch.addcmul(yc, a, dd, value=-1.0)  # y − a·d0
    wr0 = wts * r0
    ps.A[:, sl] = (wr0 * (wr0 if wts is base else r0)).sum(0)  # w² = w for 0/1 weights
    ps.cnt[:, sl] = (wts > 0).sum(0)
    ps.saa[:, sl], ps.d0[:, sl] = s_aa, dd
    if not bool(ok.all()):
        _chunk_fallback(ps, sl, yc, a, s_c, b)
    ps.lmax[:, j] = torch.where(u > 0, L, LOG_OFF).amax(-1)[:, 0]  # u > 0 ⇔ lit
    if ps.stats_acc is not None:
        e, _, st = chunk_stats(yc, a, b, t, wts, isaa_c, wa=wa)
        ps.eb[:, sl] = e
        reduce_stats(st, lab, ps.ref_k, ps.stats_acc)
