"""The observations of a Phong fit, precomputed once and processed in pixel chunks.

For shot k, pixel p, channel c (docs/design.md §2.2), with intensity i_kc, n·l, q = 1 − r·v, dist²:

    I_kcp = a_kcp·d_cp + s_c·b_kcp(α_c),   a = i·g,   b = i·u·exp(α·L)
    g_kp = max(n·l, 0)/dist²,   u_kp = [n·l > 0]/dist²,   L_kp = log max(r·v, 0) = log1p(−q)

The fit never needs more geometry than (g, u, L): three (N, 1, P) tensors
(:mod:`torchmetal.fit.grid_terms`: the renderer's formulas, built separably on the plane's pixel
grid). A subsample stores them, computed once and reused by every iteration; the full-resolution
pass (``stream=True``) stores none of them nor ``valid``, and recomputes a chunk's terms each time
it visits the chunk (:class:`~torchmetal.fit.grid_terms.GridSource`): its memory is the capture
plus a few per-pixel maps, not the capture again.
Pixels are flattened to P = h·w on a (possibly strided) grid and processed in chunks of
``chunk`` pixels, so temporaries stay (N, 3, chunk) whatever the image size. Per chunk and
shot, ``lmax`` keeps the largest L: when α·lmax < −40 the lobe is below e⁻⁴⁰ on every pixel of
the chunk, and passes skip that work.

Weights: ``valid`` (N, 3, P) uint8 0/1 = inside the mask, not saturated, n·l > 0, not an
outlier (None when streamed without robust weights or outlier masks: recomputed per chunk);
``weight`` (N, 3, P) holds IRLS weights when a robust loss or the noise model is on (else None).
Chunks see weights as floats (multiplying by a 0/1 float mask is ~6× cheaper than ``where``
on a bool mask on CPU, and uint8 → float ~4× cheaper than bool → float). Per-pixel
constants for the current weights: Σ w·a² (``saa``), the diffuse-only solution ``d0``, its exact
residual energy ``A`` = Σ w·(y − a·d0)² (one (3, 3, P) block), the observation count ``n``
(int16); Σ w·y² follows from them, = A + saa·d0² (d0 is the weighted least-squares solution:
:meth:`Observations.energy`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import torch
from torch import Tensor

from torchmetal.fit.chunk_pass import ObservationPass, as_float, observe_chunk
from torchmetal.fit.chunk_pass import tmin_chunk as tmin_chunk  # re-exported: the pass's helpers moved there
from torchmetal.fit.chunk_pass import weighted as weighted
from torchmetal.fit.grid_terms import GridSource, grid_axes, grid_geometry
from torchmetal.fit.lobes import LOG_OFF as LOG_OFF
from torchmetal.fit.lobes import geo_channels
from torchmetal.memory import pixels_per_chunk

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

ACTIVE_LOG = -40.0  # a lobe below e^-40 counts as zero
SUM_BLOCK = 1 << 16  # pixels per block of the per-element sums
ROBUST = ("huber", "cauchy")
HUBER_C = 1.345
CAUCHY_C = 2.385


def compute_dtype(x: Tensor) -> torch.dtype:
    """float64 for float64 input, else float32 (float16/bfloat16 captures compute in float32)."""
    return torch.float64 if x.dtype == torch.float64 else torch.float32


def chunk_ranges(p: int, chunk: int) -> list[tuple[int, int]]:
    chunk = max(1, int(chunk))
    return [(p0, min(p, p0 + chunk)) for p0 in range(0, p, chunk)]


def grid_stride(height: int, width: int, max_pixels: int) -> int:
    """Smallest stride s with ⌈H/s⌉·⌈W/s⌉ ≤ max_pixels."""
    s = max(1, int(math.floor(math.sqrt(height * width / max(1, max_pixels)))))
    while math.ceil(height / s) * math.ceil(width / s) > max_pixels:
        s += 1
    return s


@dataclass
class Reference:
    """A specular model to take residuals at: s, α (K, 3); with K > 1 a labeler maps pixels to K."""

    s: Tensor
    alpha: Tensor

    @property
    def k(self) -> int:
        return int(self.s.shape[0])

    def maps(self, labels: Tensor | None, n: int) -> tuple[Tensor, Tensor]:
        """(3, n) or (3, 1) s and α for pixels with ``labels`` (n,)."""
        if self.k == 1 or labels is None:
            return self.s[0].view(3, 1), self.alpha[0].view(3, 1)
        return self.s[labels].T, self.alpha[labels].T


VARIANCE_W_MIN = 1e-3  # the smallest noise weight relative to the darkest observation's (refine.noise_model)


@dataclass
class Weighting:
    """How residuals become weights: scale σ (3,), robust loss, outlier cut k·σ, IRLS rounds, and the noise
    model ``variance`` (2, 3): per channel (a, b) of the expected variance a + b·max(ŷ, 0) of an observation
    whose model value is ŷ (:func:`~torchmetal.fit.refine.noise_model`; None: every observation alike)."""

    sigma: Tensor
    robust: str | None = None
    outlier_k: float | None = None
    rounds: int = 3
    variance: Tensor | None = None

    @property
    def weighs(self) -> bool:
        """Per-observation weights are stored (robust or noise weights), not only 0/1 outlier masks."""
        return self.robust is not None or self.variance is not None

    def noise_weight(self, pred: Tensor) -> Tensor:
        """a / (a + b·max(ŷ, 0)) in [VARIANCE_W_MIN, 1] for model values ``pred`` (n, 3, c): the inverse
        variance relative to a black observation's."""
        a, b = (v.to(pred.dtype).view(1, 3, 1) for v in self.variance)
        return (a / (a + b * pred.clamp_min(0.0))).clamp_min(VARIANCE_W_MIN)

    def __call__(self, res: Tensor) -> Tensor:
        """Weights in [0, 1] for residuals (n, 3, c)."""
        z = res.abs() / self.sigma.to(res.dtype).view(1, 3, 1)
        w = torch.ones_like(z)
        if self.robust == "huber":
            w = HUBER_C / z.clamp_min(HUBER_C)
        elif self.robust == "cauchy":
            w = 1.0 / (1.0 + (z / CAUCHY_C) ** 2)
        if self.outlier_k is not None:
            w = torch.where(z > self.outlier_k, torch.zeros_like(w), w)
        return w


@dataclass
class Observations:
    """Flattened per-observation terms of a fit on an h×w pixel grid (see module docstring)."""

    y: Tensor  # (N, 3, P) images, any float dtype (cast per chunk)
    g: Tensor | None  # (N, 1, P); None when streamed (``source``)
    u: Tensor | None  # (N, 1, P)
    L: Tensor | None  # (N, 1, P)
    inten: Tensor  # (N, 3, 1)
    valid: Tensor | None  # (N, 3, P) uint8 0/1; None when streamed without weights
    weight: Tensor | None  # (N, 3, P) robust or noise weights (0 where invalid) or None
    chunks: list[tuple[int, int]]
    lmax: Tensor  # (N, n_chunks)
    saa: Tensor  # (3, P)
    d0: Tensor  # (3, P)
    A: Tensor  # (3, P)
    n: Tensor  # (3, P) int16 count of observations with a weight > 0
    fallback: Tensor  # (3, P) texture where no observation is valid (expanded zeros when there is none)
    labels: Tensor | None  # (P,) int64 from the labeler
    tmin: Tensor | None  # (3, P) T_min = min_k y/a (4.1.6), when asked for
    height: int
    width: int
    dtype: torch.dtype
    first_stats: tuple[Tensor, Tensor] | None = None  # VP stats at the reference α (with_stats)
    lobe: str = "phong"  # the specular lobe L (and geo) describe (torchmetal.fit.lobes)
    geo: Tensor | None = None  # (N, 3, P) GGX geometry (1 − n·h, n·l, n·v); None for phong/blinn or streamed
    source: GridSource | None = None  # recomputes g, u, L, geo and validity per chunk (the full-resolution pass)

    @property
    def num_shots(self) -> int:
        return int(self.y.shape[0])

    @property
    def num_pixels(self) -> int:
        return int(self.y.shape[-1])

    @property
    def device(self) -> torch.device:
        return self.y.device

    @property
    def n_obs(self) -> float:
        """Σ n over pixels and channels, at least 1: the divisor of per-observation means."""
        return max(1.0, float(self.n.sum()))

    def energy(self, k: int = 1) -> Tensor:
        """Per-element (K, 3) float64 sums of Σ w·y² = A + saa·d0² (an energy scale for relative
        thresholds; by ``labels`` if K > 1), pixel block by pixel block (no full-size temporaries)."""
        return self.element_sum(lambda sl: torch.addcmul(self.A[:, sl].double(), self.saa[:, sl].double(),
                                                         self.d0[:, sl].double() ** 2), k)

    def isaa(self, p0: int = 0, p1: int | None = None) -> Tensor:
        """1/Σ w·a² (0 where no valid observation) of pixels [p0, p1): (3, c) — per chunk, no full-size temporaries."""
        saa = self.saa[:, p0:p1]
        ok = saa > 0
        return torch.where(ok, 1.0 / torch.where(ok, saa, torch.ones_like(saa)), torch.zeros_like(saa))

    def w(self, sl: slice, shots: Tensor | None = None) -> Tensor:
        """Float weights of a chunk (n, 3, c): 0/1 validity or robust IRLS weights."""
        w = self.valid[:, :, sl] if self.weight is None else self.weight[:, :, sl]
        w = w if shots is None else w.index_select(0, shots)
        return w.to(self.dtype)

    def chunk(self, j: int, shots: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """(y, g, u, L, w, inten) of chunk j, restricted to ``shots`` (index tensor) if given."""
        p0, p1 = self.chunks[j]
        sl = slice(p0, p1)
        y, inten = self.y[:, :, sl], self.inten
        if shots is not None:
            y, inten = y.index_select(0, shots), inten.index_select(0, shots)
        if self.source is not None:
            g, u, L, _, base = self.source.terms(p0, p1, shots)
            w = as_float(base, self.dtype) if self.valid is None and self.weight is None else self.w(sl, shots)
            return y.to(self.dtype), g, u, L, w, inten
        g, u, L = self.g[:, :, sl], self.u[:, :, sl], self.L[:, :, sl]
        if shots is not None:
            g, u, L = (t.index_select(0, shots) for t in (g, u, L))
        return y.to(self.dtype), g, u, L, self.w(sl, shots), inten

    def geo_chunk(self, j: int, shots: Tensor | None = None) -> Tensor | None:
        """The lobe geometry (n, 3, c) of chunk j (restricted to ``shots``), None for phong/blinn."""
        p0, p1 = self.chunks[j]
        if self.source is not None:
            return self.source.terms(p0, p1, shots)[3]
        if self.geo is None:
            return None
        geo = self.geo[:, :, p0:p1]
        return geo if shots is None else geo.index_select(0, shots)

    def dense(self) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
        """(g, u, L) (N, 1, P) and geo (N, 3, P) or None, whole — for small problems (tests, diagnostics)."""
        if self.source is None:
            return self.g, self.u, self.L, self.geo
        parts = [self.source.terms(p0, p1)[:4] for p0, p1 in self.chunks]
        geo = None if parts[0][3] is None else torch.cat([q[3] for q in parts], -1)
        return (*(torch.cat([q[i] for q in parts], -1) for i in range(3)), geo)

    def active_shots(self, alpha_lo: float) -> Tensor:
        """(N, n_chunks) bool: the lobe can exceed e^-40 somewhere in the chunk for α ≥ alpha_lo."""
        return alpha_lo * self.lmax > ACTIVE_LOG

    def element_sum(self, x: Tensor | Callable[[slice], Tensor], k: int) -> Tensor:
        """Per-pixel (3, P) → per-element (K, 3) float64 sums over pixels (by ``labels`` if K > 1), in
        blocks of :data:`SUM_BLOCK` pixels (no float64 copy of the whole map). ``x`` may be a function
        of a pixel slice returning that block."""
        block = x if callable(x) else (lambda sl: x[:, sl].double())
        out = torch.zeros(3, k, dtype=torch.float64, device=self.device)
        p = self.num_pixels
        for p0 in range(0, p, SUM_BLOCK):
            sl = slice(p0, min(p, p0 + SUM_BLOCK))
            if k == 1:
                out[:, 0] += block(sl).sum(-1)
            else:
                out.index_add_(1, self.labels[sl], block(sl))
        return out.T.contiguous()


def build_observations(
    capture: Capture, *, stride: int = 1, shots: list[int] | None = None, dtype: torch.dtype | None = None,
    chunk: int | None = None, ref: Reference | None = None, weighting: Weighting | None = None,
    labeler: Callable[[Tensor, Tensor], Tensor] | None = None, want_tmin: bool = False, with_stats: bool = False,
    lobe: str = "phong", window: tuple[slice, slice] | None = None, stream: bool = False,
) -> Observations:
    """Precompute the observations of ``capture`` on a pixel grid of the given stride.

    Args:
        capture: a Capture (images (N,3,H,W), normals, mask, saturated, lights, intensities,
            cameras, size).
        stride: keep pixels (off + i·stride, off + j·stride), off = stride // 2 (1: all).
        shots: shot indices to use (default all).
        dtype: compute dtype (default float64 for float64 images, else float32).
        chunk: pixels per chunk; None: :func:`~torchmetal.memory.pixels_per_chunk`.
        ref: specular model at which residuals are taken for ``weighting`` (and the fallback).
        weighting: turn residuals at ``ref`` into weights (per-pixel IRLS of the texture,
            ``weighting.rounds`` rounds, inside each chunk).
        labeler: (T_min (3, c), full-resolution pixel coordinates (row, col) (2, c)) → labels
            (c,) int64, for clustered ``ref`` and ``labels``.
        want_tmin: keep T_min (3, P).
        with_stats: also compute the variable-projection stats at ``ref``'s α in the same pass
            (``first_stats``: (stats (6, K, 3), e_b (3, P)) for :func:`~torchmetal.fit.refine.fit_specular`).
        lobe: the specular lobe, one of :data:`torchmetal.lobes.LOBES` (L and geo follow it).
        window: (rows, cols) slices of full-resolution pixels to use instead of the stride grid
            (a tile of a tiled fit: the same values as those pixels of the whole grid).
        stream: store no per-observation geometry (nor ``valid`` without weights): chunks recompute
            it (:class:`~torchmetal.fit.grid_terms.GridSource`) — the same values, for a
            full-resolution pass whose stored geometry would weigh as much as the capture.

    Returns:
        :class:`Observations`.
    """
    imgs = capture.images
    dt = dtype or compute_dtype(imgs)
    rows, cols = _grid_slices(imgs, stride, window)
    idx = None if shots is None else torch.as_tensor(shots, dtype=torch.long, device=imgs.device)
    y, sat, mask, h, w = _grid_pixels(capture, rows, cols, idx)
    lights, cams, inten = _shot_terms(capture, idx, dt, int(y.shape[0]))
    chunk = pixels_per_chunk(capture) if chunk is None else chunk
    chunks = chunk_ranges(h * w, chunk)
    ps = _start_pass(y, inten, mask, sat, rows, cols, w, dt, len(chunks), ref=ref, weighting=weighting, labeler=labeler,
                     want_tmin=want_tmin, with_stats=with_stats, stream=stream, lobe=lobe)
    _pass_geometry(ps, capture, lights, cams, chunk, stream)
    for j, (p0, p1) in enumerate(chunks):
        observe_chunk(ps, j, p0, p1)
    return Observations(
        y=y, g=ps.g, u=ps.u, L=ps.L, inten=inten, valid=ps.valid, weight=ps.weight, chunks=chunks, lmax=ps.lmax,
        saa=ps.saa, d0=ps.d0, A=ps.A, n=ps.cnt,
        fallback=torch.zeros(3, 1, dtype=dt, device=imgs.device).expand(3, h * w) if ps.fb is None else ps.fb,
        labels=ps.labels, tmin=ps.tmin, height=h, width=w, dtype=dt,
        first_stats=None if ps.stats_acc is None else (ps.stats_acc.permute(0, 2, 1).contiguous(), ps.eb),
        lobe=lobe, geo=ps.geo, source=ps.source,
    )


def _grid_slices(imgs: Tensor, stride: int, window: tuple[slice, slice] | None) -> tuple[slice, slice]:
    """(rows, cols) of full-resolution pixels: the stride grid (offset stride // 2), or ``window``."""
    big_h, big_w = int(imgs.shape[-2]), int(imgs.shape[-1])
    off = stride // 2 if stride > 1 else 0
    rows, cols = slice(off, big_h, stride), slice(off, big_w, stride)
    if window is not None:
        rows, cols = (slice(*s.indices(n)) for s, n in zip(window, (big_h, big_w)))
    return rows, cols


def _on_grid(t: Tensor, rows: slice, cols: slice, idx: Tensor | None) -> Tensor:
    t = t[..., rows, cols]
    return t if idx is None else t.index_select(0, idx)


def _grid_pixels(capture: Capture, rows: slice, cols: slice,
                 idx: Tensor | None) -> tuple[Tensor, Tensor | None, Tensor | None, int, int]:
    """(y (N, 3, P), saturated (N, 3, P) or None when nothing is clipped, mask (1, 1, P) or None when every pixel
    is inside, h, w) of the grid's pixels and the shots ``idx``."""
    y4 = _on_grid(capture.images, rows, cols, idx)
    n_shots, _, h, w = y4.shape
    p = h * w
    y = y4.reshape(n_shots, 3, p)
    sat = _on_grid(capture.saturated, rows, cols, idx).reshape(n_shots, 3, p) if capture.saturated is not None else None
    mask = capture.mask[..., rows, cols].reshape(1, 1, p).bool() if capture.mask is not None else None
    if sat is not None and not bool(sat.view(torch.uint8).amax()):  # nothing clipped (uint8 amax: 10× cheaper than any)
        sat = None
    if mask is not None and bool(mask.view(torch.uint8).amin()):  # every pixel inside
        mask = None
    return y, sat, mask, h, w


def _shot_terms(capture: Capture, idx: Tensor | None, dt: torch.dtype, n_shots: int) -> tuple[Tensor, Tensor, Tensor]:
    """(lights, cameras, intensities (N, 3, 1)) of the shots ``idx`` in the working dtype."""
    lights = capture.lights.to(dt)
    cams = capture.cameras.to(dt)
    inten = capture.intensities.to(dt)
    if idx is not None:
        lights, cams, inten = lights[idx], cams[idx], inten[idx]
    return lights, cams, inten.view(n_shots, 3, 1)


def _start_pass(y: Tensor, inten: Tensor, mask: Tensor | None, sat: Tensor | None, rows: slice, cols: slice, w: int,
                dt: torch.dtype, n_chunks: int, *, ref: Reference | None, weighting: Weighting | None,
                labeler: Callable[[Tensor, Tensor], Tensor] | None, want_tmin: bool, with_stats: bool, stream: bool,
                lobe: str) -> ObservationPass:
    """The pass's inputs and its (empty) maps: only those asked for."""
    n_shots, _, p = y.shape
    dev = y.device
    new = lambda *shape, dtype=dt: torch.empty(*shape, dtype=dtype, device=dev)  # noqa: E731
    weighs = weighting is not None and weighting.weighs  # per-observation weights stored (robust or noise)
    valid_all = new(n_shots, 3, p, dtype=torch.uint8) if not stream or weighting is not None else None
    wstore = torch.float16 if dt == torch.float32 else torch.float32
    weight_all = new(n_shots, 3, p, dtype=wstore) if weighs else None
    saa, d0, A = new(3, 3, p).unbind(0)
    cnt = new(3, p, dtype=torch.int16 if n_shots < 2**15 else torch.int32)  # a count per pixel and channel
    lmax = new(n_shots, n_chunks)
    labels = torch.zeros(p, dtype=torch.long, device=dev) if labeler is not None else None
    tmin_all = new(3, p) if want_tmin else None
    stats_acc = eb_all = None
    if with_stats and ref is not None:
        stats_acc = torch.zeros(6, 3, ref.k, dtype=torch.float64, device=dev)
        eb_all = new(3, p)
    # the working dtype: a float64 s, α would promote every (n, 3, c) temporary
    ref_dt = None if ref is None else Reference(ref.s.to(dt), ref.alpha.to(dt))
    return ObservationPass(
        y=y, inten=inten, inten_pos=inten > 0, mask=mask, sat=sat, rows=rows, cols=cols, width=w, dt=dt,
        zero=torch.zeros((), dtype=dt, device=dev), ref=ref_dt, ref_k=0 if ref is None else ref.k, weighting=weighting,
        weighs=weighs, labeler=labeler, want_tmin=want_tmin, lobe=lobe, valid=valid_all, weight=weight_all, wstore=wstore,
        saa=saa, d0=d0, A=A, cnt=cnt, lmax=lmax, labels=labels, tmin=tmin_all, stats_acc=stats_acc, eb=eb_all,
    )


def _pass_geometry(ps: ObservationPass, capture: Capture, lights: Tensor, cams: Tensor, chunk: int, stream: bool) -> None:
    """The pass's geometry: a :class:`GridSource` that recomputes it per chunk (``stream``), else (g, u, L, geo)
    computed once and stored."""
    dt, rows, cols, lobe = ps.dt, ps.rows, ps.cols, ps.lobe
    if stream:
        xs, ys, normals = grid_axes(capture, rows, cols, dt)
        ps.source = GridSource(lights, cams, xs, ys, None if normals is None else normals.to(dt), lobe, ps.inten_pos,
                               ps.mask, ps.sat, dt)
        return
    n_shots, _, p = ps.y.shape
    new = lambda *shape: torch.empty(*shape, dtype=dt, device=ps.y.device)  # noqa: E731
    ps.g, ps.u, ps.L = new(n_shots, 1, p), new(n_shots, 1, p), new(n_shots, 1, p)
    ps.geo = new(n_shots, 3, p) if geo_channels(lobe) else None
    grid_geometry(capture, rows, cols, lights, cams, dt, max(1, chunk // ps.width), out=(ps.g, ps.u, ps.L), lobe=lobe,
                  geo_out=ps.geo)
