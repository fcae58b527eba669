"""The sample's own flakes: flakes seen glinting in the fit shots, kept where they are.

The statistical field (:mod:`torchmetal.flakes.field`) draws flakes at random, so a held-out shot
of the same sample shows its glints where the field has none, and the field glints where the
photo does not: on the zoo's flake scenes that rendered 2–4 dB worse than no flakes at all. Here
each associated flake of the flake stage (:class:`~torchmetal.flakes.results.FlakeStageResult`
``flake_id``) is measured and kept (:class:`ObservedFlakes`):

- position: the amplitude-weighted mean centroid of its detections (px, pixel i spans [i, i+1));
- footprint: an ellipse of the brightest detection's flux/peak area, aspect and angle, drawn with
  the statistical field's anti-aliased ramp (Σ weight = area);
- normal: the amplitude-weighted mean of the unit half vectors of the shots where it glints, refined
  by their amplitude ratios, then placed by the flakes' known brightness and the shots that missed it
  (:func:`~torchmetal.flakes.placement.place_normals`: a faint glint is a flake seen at its tail);
- colour: the least-squares glint reflectance c of the detections' peak colours, given the
  footprint's peak weight and each shot's glint factor exp(−|m − h|² / 2σ_g²).

:func:`material_flake_field` renders them with the statistical field filling only what no fit
shot observed: a statistical flake is dropped where it overlaps an observed one, and where some
fit shot would have detected it, had it been there: its peak glint amplitude (channel-mean colour ×
footprint peak) times that shot's glint factor exp(−|m − h|² / 2σ_g²) reaches ``detect_amp``, the
amplitude the fit shots' detector fires at (the least SNR of the detections × their median local σ).
The fit shots find flakes far off their glint peak: on zoo flakes_b (256²) every true flake whose
best fit-shot glint factor was ≥ 0.1 was observed (18 of 19 in [0.05, 0.1)), so the former fixed
cut at a factor of ``PROBED_GLINT`` = 0.5 (kept now only for observed flakes saved without
``detect_amp``) refilled that whole band with random flakes, which glinted in held-out views
between the fit shots: 58 of the 65 predicted sparkles with no true glint within 2 px came from
the fill (count ratio 1.28). With a coarse density map (glitter on part of the sample)
the fill is thinned cell by cell. Pixels beyond the observed sample (a tiled texture) are all
fill. Everything is light-independent and deterministic, so the renderer bakes it once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchmetal.errors import MaterialError
from torchmetal.flakes.field import FlakeField, field_cell, flake_field, hash_uniform
from torchmetal.flakes.model import MAX_COLOR, FlakeModel
from torchmetal.flakes.placement import MIN_AMP_STD, place_normals
from torchmetal.geometry import normalize, shading_geometry

__all__ = ["ObservedFlakes", "observed_flakes", "observed_field", "material_flake_field", "PROBED_GLINT",
           "ARRAYS"]

PROBED_GLINT = 0.5  # without ``detect_amp``: glint factor at which a fit shot would have seen a flake
DENSITY_CELL = 32  # px: cell of the coarse flake-density map
DENSITY_DISPERSION = 2.0  # variance/mean of the cell counts above which the glitter is patchy (Poisson: 1)
MIN_FLAKES_MAP = 20  # fewer observed flakes: no density map

#: array name → (attribute, file name): the material directory's files (docs/design.md §2.3)
ARRAYS = {
    "position": "flakes_position.npy", "axes": "flakes_axes.npy", "angle": "flakes_angle.npy",
    "normal": "flakes_normal.npy", "color": "flakes_color.npy", "probe_lights": "flakes_probe_lights.npy",
    "probe_cameras": "flakes_probe_cameras.npy", "density": "flakes_density.npy",
}


@dataclass
class ObservedFlakes:
    """The J flakes the fit shots saw, float32 tensors.

    position (J, 2) centre (row, col) in px; axes (J, 2) semi-major, semi-minor (px, the
    field's ellipse before its anti-aliasing shrink); angle (J,) radians from +col towards up;
    normal (J, 3) unit world flake normal; color (J, 3) linear glint reflectance;
    probe_lights, probe_cameras (N, 4): the fit shots (whose glints were looked for);
    density (gh, gw) coarse flake density relative to the sample mean, or None (uniform);
    shape (H, W): the texture they were observed on; detect_amp: the peak glint amplitude
    (channel mean, reflectance units) the fit shots detect, or None (unknown: ``PROBED_GLINT``).
    """

    position: Tensor
    axes: Tensor
    angle: Tensor
    normal: Tensor
    color: Tensor
    probe_lights: Tensor
    probe_cameras: Tensor
    shape: tuple[int, int]
    density: Tensor | None = None
    detect_amp: float | None = None

    def __post_init__(self) -> None:
        j = int(self.position.shape[0]) if self.position.dim() == 2 else -1
        want = {"position": (j, 2), "axes": (j, 2), "angle": (j,), "normal": (j, 3), "color": (j, 3)}
        for name, shape in want.items():
            v = getattr(self, name)
            if not isinstance(v, Tensor) or tuple(v.shape) != shape:
                raise MaterialError(f"observed flakes {name}: expected shape {shape}, found "
                                    f"{tuple(getattr(v, 'shape', ()))}")
            if not bool(torch.isfinite(v).all()):
                raise MaterialError(f"observed flakes {name}: expected finite values, found NaN/Inf")
        for name in ("probe_lights", "probe_cameras"):
            v = getattr(self, name)
            if not isinstance(v, Tensor) or v.dim() != 2 or v.shape[1] != 4 or not bool(torch.isfinite(v).all()):
                raise MaterialError(f"observed flakes {name}: expected finite (N, 4), found {tuple(getattr(v, 'shape', ()))}")
        if self.probe_lights.shape != self.probe_cameras.shape:
            raise MaterialError(f"observed flakes probes: expected lights and cameras of the same shape, found "
                                f"{tuple(self.probe_lights.shape)} and {tuple(self.probe_cameras.shape)}")
        if self.density is not None and (self.density.dim() != 2 or not bool(torch.isfinite(self.density).all())
                                         or bool((self.density < 0).any())):
            raise MaterialError(f"observed flakes density: expected a finite (gh, gw) map >= 0, found "
                                f"{tuple(self.density.shape)}")
        if bool((self.axes <= 0).any()) or bool((self.color < 0).any()) or bool((self.color > MAX_COLOR).any()):
            raise MaterialError(f"observed flakes: expected axes > 0 and colours in [0, {MAX_COLOR:g}]")
        if self.detect_amp is not None:
            if isinstance(self.detect_amp, bool) or not isinstance(self.detect_amp, (int, float)) \
                    or not (math.isfinite(self.detect_amp) and self.detect_amp > 0):
                raise MaterialError(f"observed flakes detect_amp: expected a finite number > 0 or None, "
                                    f"found {self.detect_amp!r}")
            self.detect_amp = float(self.detect_amp)
        self.shape = (int(self.shape[0]), int(self.shape[1]))

    def __len__(self) -> int:
        return int(self.position.shape[0])

    def arrays(self) -> dict[str, Tensor]:
        """name → tensor of :data:`ARRAYS` (density only when present)."""
        out = {k: getattr(self, k) for k in ARRAYS}
        if self.density is None:
            out.pop("density")
        return out


# ----------------------------------------------------------------------------- estimation


def _ellipse_axes(area: Tensor, aspect: Tensor) -> tuple[Tensor, Tensor]:
    """Semi-axes of the field's footprint with Σ weight = area (the field's anti-aliasing shrink)."""
    a = torch.sqrt(area / (math.pi * aspect))
    b = aspect * a
    k = torch.sqrt((1.0 - 1.0 / (12.0 * b * b)).clamp_min(0.25))
    return a * k, b * k


def _footprints(position: Tensor, axes: Tensor, angle: Tensor, height: int, width: int):
    """Anti-aliased ellipse weights of every flake on its (2R+1)² patch.

    Returns (flake (M,), flat pixel index (M,), weight (M,)) for the candidate pixels inside the
    texture with weight > 0.
    """
    j = position.shape[0]
    dt = position.dtype
    a, b = axes[:, 0], axes[:, 1]
    r = int(math.ceil(float(a.max()))) + 1 if j else 1
    off = torch.arange(-r, r + 1, device=position.device)
    oi, oj = torch.meshgrid(off, off, indexing="ij")
    row = position[:, 0].floor().long().view(-1, 1, 1) + oi
    col = position[:, 1].floor().long().view(-1, 1, 1) + oj
    dy = row.to(dt) + 0.5 - position[:, 0].view(-1, 1, 1)
    dx = col.to(dt) + 0.5 - position[:, 1].view(-1, 1, 1)
    th = angle.view(-1, 1, 1)
    along = dx * torch.cos(th) - dy * torch.sin(th)
    across = dx * torch.sin(th) + dy * torch.cos(th)
    rho = torch.sqrt((along / a.view(-1, 1, 1)) ** 2 + (across / b.view(-1, 1, 1)) ** 2)
    wt = ((1.0 - rho) * b.view(-1, 1, 1) + 0.5).clamp(0.0, 1.0)
    inside = (row >= 0) & (row < height) & (col >= 0) & (col < width) & (wt > 0)
    flake = torch.arange(j, device=position.device).view(-1, 1, 1).expand_as(row)
    return flake[inside], (row * width + col)[inside], wt[inside]


def _density_map(position: Tensor, height: int, width: int) -> Tensor | None:
    """(gh, gw) counts/mean of the observed flakes in DENSITY_CELL cells (3×3 box smoothed), or None
    when the counts are Poisson-like (variance/mean ≤ DENSITY_DISPERSION) or too few flakes."""
    gh, gw = max(1, -(-height // DENSITY_CELL)), max(1, -(-width // DENSITY_CELL))
    if len(position) < MIN_FLAKES_MAP or gh * gw < 4:
        return None
    ci = (position[:, 0] / DENSITY_CELL).floor().long().clamp(0, gh - 1)
    cj = (position[:, 1] / DENSITY_CELL).floor().long().clamp(0, gw - 1)
    counts = torch.bincount(ci * gw + cj, minlength=gh * gw).double()
    mean = counts.mean()
    if float(counts.var(unbiased=True) / mean) <= DENSITY_DISPERSION:
        return None
    box = torch.nn.functional.avg_pool2d(counts.view(1, 1, gh, gw), 3, 1, 1, count_include_pad=False)[0, 0]
    return (box / box.mean().clamp_min(1e-12)).to(torch.float32)


def _refine_normals(m0: Tensor, hk: Tensor, fid: Tensor, amp: Tensor, snr: Tensor, sigma: float,
                    iters: int = 3, max_step: float = 3.0, max_total: float = 2.0) -> Tensor:
    """Flake normals (J, 3) from the glint amplitudes of their detections, starting at ``m0``.

    log a_k = c₀ − |m − h_k|² / 2σ² is linear in (c₀, δ) for m = m₀ + σ·δ (δ in m₀'s tangent
    plane): Gauss–Newton steps of the weighted least squares (weights snr², the inverse variance
    of log a) with a unit ridge on δ (a flake seen in one shot keeps the half vector of that
    shot; two shots place it between them by their amplitude ratio). Steps are clipped to
    ``max_step``·σ and the normal stays within ``max_total``·σ of ``m0``. ``hk`` (P, 3) half vectors, ``fid`` (P,) flake, ``amp``/``snr`` (P,).
    """
    j = m0.shape[0]
    wt = snr.clamp(1.0, 100.0) ** 2
    y_obs = torch.log(amp)
    m = m0
    for _ in range(iters):
        ref = torch.zeros_like(m)
        ref[:, 0] = 1.0
        alt = torch.zeros_like(m)
        alt[:, 1] = 1.0
        ref = torch.where((m[:, :1].abs() > 0.9), alt, ref)
        t1 = normalize(ref - (ref * m).sum(1, keepdim=True) * m, dim=1)
        t2 = torch.cross(m, t1, dim=1)
        d = m[fid] - hk  # (P, 3)
        x = torch.stack([torch.ones_like(wt), -(d * t1[fid]).sum(1) / sigma, -(d * t2[fid]).sum(1) / sigma], 1)
        y = y_obs + (d * d).sum(1) / (2 * sigma * sigma)
        a = torch.zeros(j, 3, 3, dtype=m.dtype).index_add_(0, fid, wt.view(-1, 1, 1) * x.unsqueeze(2) * x.unsqueeze(1))
        a = a + torch.diag(torch.tensor([1e-9, 1.0, 1.0], dtype=m.dtype))
        rhs = torch.zeros(j, 3, dtype=m.dtype).index_add_(0, fid, (wt * y).unsqueeze(1) * x)
        sol = torch.linalg.solve(a, rhs)
        step = sol[:, 1:]
        norm = step.norm(dim=1, keepdim=True)
        step = step * (max_step / norm.clamp_min(max_step)).clamp(max=1.0)
        m = normalize(m + sigma * (step[:, :1] * t1 + step[:, 1:] * t2), dim=1)
        # never further than max_total·σ from the start: amplitude ratios extrapolate badly
        off = m - m0
        far = off.norm(dim=1, keepdim=True)
        m = normalize(m0 + off * (max_total * sigma / far.clamp_min(max_total * sigma)), dim=1)
    return m


def observed_flakes(capture, particles, flake_id: Tensor, model: FlakeModel) -> ObservedFlakes | None:
    """Measure and keep every associated flake of the flake stage.

    Args:
        capture: the fitted :class:`~torchmetal.io.capture.Capture` (normals, lights, cameras, size).
        particles: the stage's :class:`~torchmetal.flakes.results.Particles` (P rows).
        flake_id: (P,) associated flake of each particle, −1 for particles left out.
        model: the fitted :class:`FlakeModel` (its ``glint_sigma``).

    Returns:
        :class:`ObservedFlakes`, or None when no particle is associated.
    """
    h, w = capture.images.shape[-2:]
    if flake_id is None or len(particles) == 0 or not bool((flake_id >= 0).any()):
        return None
    dt = torch.float64
    keep = torch.nonzero(flake_id >= 0, as_tuple=True)[0]
    p = particles.select(keep)
    fid = torch.unique(flake_id[keep], return_inverse=True)[1]
    j = int(fid.max()) + 1
    amp = p.amp.to(dt).clamp_min(1e-12)
    wsum = torch.zeros(j, dtype=dt).index_add_(0, fid, amp)
    cy = torch.zeros(j, dtype=dt).index_add_(0, fid, amp * p.cy.to(dt)) / wsum
    cx = torch.zeros(j, dtype=dt).index_add_(0, fid, amp * p.cx.to(dt)) / wsum
    # the brightest detection's shape (the least noisy)
    best = torch.full((j,), -1.0, dtype=dt).scatter_reduce(0, fid, p.snr.to(dt), "amax")
    is_best = p.snr.to(dt) == best[fid]
    first = torch.full((j,), len(p), dtype=torch.int64).scatter_reduce(
        0, fid[is_best], torch.arange(len(p))[is_best], "amin")
    b = p.select(first)
    area = (b.flux.to(dt) / b.amp.to(dt).clamp_min(1e-12)).clamp(0.25, 50.0)
    lam1 = (b.major.to(dt) / 4) ** 2 - 1.0 / 12.0
    lam2 = (b.minor.to(dt) / 4) ** 2 - 1.0 / 12.0
    aspect = torch.sqrt(lam2.clamp_min(1e-3) / lam1.clamp_min(1e-3)).clamp(0.2, 1.0)
    a_ax, b_ax = _ellipse_axes(area, aspect)
    axes = torch.stack([a_ax, b_ax], 1)
    # half vectors of every detection's shot at its flake's centre pixel
    row = cy.floor().long().clamp(0, h - 1)
    col = cx.floor().long().clamp(0, w - 1)
    y = (0.5 - cy / h) * capture.size[1]
    x = (cx / w - 0.5) * capture.size[0]
    pts = torch.stack([x, y, torch.zeros_like(x)]).unsqueeze(1)  # (3, 1, J)
    nrm = capture.normals.to(dt)[:, row, col].unsqueeze(1)
    one = torch.ones_like(capture.intensities, dtype=dt)
    half = shading_geometry(nrm, capture.lights.to(dt), one, capture.cameras.to(dt), points=pts).half[:, :, 0]  # (N, 3, J)
    hk = half[p.shot, :, fid]  # (P, 3)
    normal = normalize(torch.zeros(j, 3, dtype=dt).index_add_(0, fid, amp.unsqueeze(1) * hk), dim=1)
    sig = float(model.glint_sigma)
    normal = _refine_normals(normal, hk, fid, amp, p.snr.to(dt), sig)
    detect_amp = _detect_amp(particles)
    prior = (model.extra.get("log_amp_mean"), model.extra.get("log_amp_std"))
    if detect_amp is not None and None not in prior:  # the flakes' brightness places tail-seen ones
        n_shot = half.shape[0]
        flat = p.shot * j + fid  # a flake detected twice in a shot: its brightest detection
        det = torch.zeros(n_shot * j, dtype=torch.bool).index_fill_(0, flat, True).view(n_shot, j)
        log_a = torch.full((n_shot * j,), -50.0, dtype=dt).scatter_reduce(0, flat, torch.log(amp), "amax").view(n_shot, j)
        wt = torch.zeros(n_shot * j, dtype=dt).scatter_reduce(0, flat, p.snr.to(dt).clamp(1.0, 100.0) ** 2, "amax")
        valid = capture.mask[0, row, col].cpu().unsqueeze(0) & ~capture.saturated[:, :, row, col].any(1).cpu()
        normal = place_normals(normal, half, det, valid, log_a, wt.view(n_shot, j), sig, float(prior[0]),
                               float(prior[1]), detect_amp)
    # colour: peak colour = c · w_peak · g_k  →  least squares over the detections
    g = torch.exp(-((normal[fid] - hk) ** 2).sum(1) / (2.0 * sig * sig))  # (P,)
    flake, _, wt = _footprints(torch.stack([cy, cx], 1), axes, b.angle.to(dt), h, w)
    w_peak = torch.zeros(j, dtype=dt).scatter_reduce(0, flake, wt, "amax").clamp_min(0.05)
    num = torch.zeros(j, 3, dtype=dt).index_add_(0, fid, g.unsqueeze(1) * p.peak.to(dt).clamp_min(0.0))
    den = torch.zeros(j, dtype=dt).index_add_(0, fid, g * g).clamp_min(1e-12)
    color = num / (den * w_peak).unsqueeze(1)
    # a glint factor ≥ 1/2 at the brightest detection: c ≤ 2·peak/w_peak (a normal placed far off
    # the detections' half vectors must not turn a faint detection into a bright flake), or, with the
    # flakes' brightness known, up to its mean + 2 spreads (a flake placed by it)
    top = torch.zeros(j, 3, dtype=dt).scatter_reduce_(0, fid.view(-1, 1).expand(-1, 3), p.peak.to(dt).clamp_min(0.0), "amax")
    scale = torch.full((j,), 2.0, dtype=dt)
    if detect_amp is not None and None not in prior:
        a_top = torch.zeros(j, dtype=dt).scatter_reduce(0, fid, amp, "amax")
        bright = math.exp(float(prior[0]) + 2.0 * max(float(prior[1]), MIN_AMP_STD))
        scale = torch.maximum(scale, bright / a_top)
    color = torch.minimum(color, scale.unsqueeze(1) * top / w_peak.unsqueeze(1)).clamp(0.0, MAX_COLOR)
    f32 = torch.float32
    position = torch.stack([cy, cx], 1)
    return ObservedFlakes(
        position=position.to(f32), axes=axes.to(f32), angle=b.angle.to(f32), normal=normal.to(f32),
        color=color.to(f32), probe_lights=capture.lights.to(f32).cpu(), probe_cameras=capture.cameras.to(f32).cpu(),
        shape=(h, w), density=_density_map(position, h, w), detect_amp=detect_amp,
    )


def _detect_amp(particles) -> float | None:
    """The peak glint amplitude the detector fires at: the least SNR of all the stage's detections
    (its threshold k_hi) × their median local σ; None when there is none to measure."""
    sigma, snr = particles.sigma.double(), particles.snr.double()
    ok = torch.isfinite(sigma) & torch.isfinite(snr) & (sigma > 0) & (snr > 0)
    if not bool(ok.any()):
        return None
    return float(snr[ok].min() * sigma[ok].median())


# ----------------------------------------------------------------------------- rendering


def observed_field(obs: ObservedFlakes, height: int, width: int, normals: Tensor, glint_sigma: float) -> FlakeField:
    """The observed flakes as per-pixel maps on an H×W texture (dtype/device of ``normals`` (3, H, W)).

    Where two footprints overlap, the pixel takes the flake of the larger weight (ties: the lower index).
    """
    dt, dev = normals.dtype, normals.device
    weight = torch.zeros(height * width, dtype=dt, device=dev)
    normal = normals.reshape(3, -1).clone()
    color = torch.zeros(3, height * width, dtype=dt, device=dev)
    if len(obs):
        flake, pix, wt = _footprints(obs.position.to(dev, dt), obs.axes.to(dev, dt), obs.angle.to(dev, dt), height, width)
        top = torch.zeros_like(weight).scatter_reduce(0, pix, wt, "amax")
        win = wt >= top[pix]
        owner = torch.full((height * width,), len(obs), dtype=torch.int64, device=dev).scatter_reduce(
            0, pix[win], flake[win], "amin")
        sel = owner < len(obs)
        weight[sel] = top[sel]
        normal[:, sel] = obs.normal.to(dev, dt).t()[:, owner[sel]]
        color[:, sel] = obs.color.to(dev, dt).t()[:, owner[sel]]
    shape = (height, width)
    return FlakeField(weight.view(1, *shape), normal.view(3, *shape), color.view(3, *shape), float(glint_sigma), len(obs))


def _fill_keep(model: FlakeModel, stat: FlakeField, obs: ObservedFlakes, occupied: Tensor, normals: Tensor,
               size: tuple[float, float]) -> tuple[Tensor, int]:
    """(H, W) bool: statistical-field pixels to keep, decided per hash cell (one flake each), and the
    number of statistical flakes kept."""
    h, w = occupied.shape
    c = field_cell(model)  # the field's own cells (sized for a density map's densest block)
    gw = -(-w // c)
    cell = ((torch.arange(h, device=occupied.device) // c).view(-1, 1) * gw
            + (torch.arange(w, device=occupied.device) // c).view(1, -1)).reshape(-1)
    ncell = int(cell.max()) + 1
    on = stat.weight[0].reshape(-1) > 0
    oh, ow = obs.shape
    inside = ((torch.arange(h, device=occupied.device) < oh).view(-1, 1)
              & (torch.arange(w, device=occupied.device) < ow).view(1, -1)).reshape(-1)
    drop = torch.zeros(ncell, dtype=torch.bool, device=occupied.device)
    idx = torch.nonzero(on & inside, as_tuple=True)[0]
    if idx.numel():
        # probed: some fit shot's half vector came within the glint width of the flake's normal
        rows, cols = idx // w, idx % w
        dt = normals.dtype
        x = (cols.to(dt) + 0.5) / w * size[0] - 0.5 * size[0]
        y = 0.5 * size[1] - (rows.to(dt) + 0.5) / h * size[1]
        pts = torch.stack([x, y, torch.zeros_like(x)]).unsqueeze(1)
        lights, cams = obs.probe_lights.to(normals.device, dt), obs.probe_cameras.to(normals.device, dt)
        half = shading_geometry(normals.reshape(3, -1)[:, idx].unsqueeze(1), lights, torch.ones_like(lights[:, :3]),
                                cams, points=pts).half[:, :, 0]  # (N, 3, M)
        m = stat.normal.reshape(3, -1)[:, idx].unsqueeze(0)
        g = torch.exp(-((m - half) ** 2).sum(1) / (2.0 * stat.glint_sigma**2)).amax(0)  # (M,)
        if obs.detect_amp is None:
            seen = g >= PROBED_GLINT
        else:  # the cell's flake is dropped when its brightest pixel would have been detected
            amp = stat.weight.reshape(-1)[idx] * stat.color.reshape(3, -1)[:, idx].mean(0)
            seen = amp * g >= obs.detect_amp
        bad = seen | occupied.reshape(-1)[idx]
        drop.scatter_reduce_(0, cell[idx], bad, "amax")
        if obs.density is not None:  # patchy glitter: thin the fill cell by cell
            gh_, gw_ = obs.density.shape
            dr = (rows * gh_ // oh).clamp(max=gh_ - 1)
            dc = (cols * gw_ // ow).clamp(max=gw_ - 1)
            ratio = obs.density.to(normals.device, dt)[dr, dc]
            u = hash_uniform(cell[idx] // gw, cell[idx] % gw, model.seed, 12, dt)
            drop.scatter_reduce_(0, cell[idx], u >= ratio, "amax")
    keep = on & ~drop[cell]
    return keep.view(h, w), int(torch.unique(cell[keep]).numel())


def material_flake_field(model: FlakeModel, obs: ObservedFlakes | None, height: int, width: int,
                         normals: Tensor, size: tuple[float, float]) -> FlakeField:
    """The flake field a material renders: the observed flakes where they are, the statistical field
    (seeded by ``model``) filling what no fit shot observed (see the module docstring).

    Args:
        model: the flake statistics; obs: the observed flakes (None: the statistical field alone).
        height, width: texture size; normals: (3, H, W) surface normals; size: (width, height)
            of the surface in scene units (the fit shots' half vectors).
    """
    stat = flake_field(model, height, width, normals)
    if obs is None:
        return stat
    own = observed_field(obs, height, width, normals, model.glint_sigma)
    occupied = torch.nn.functional.max_pool2d((own.weight > 0).to(normals.dtype).unsqueeze(0), 3, 1, 1)[0, 0] > 0
    keep, kept = _fill_keep(model, stat, obs, occupied, normals, size)
    keep = keep.unsqueeze(0)
    use_own = own.weight > 0
    weight = torch.where(use_own, own.weight, torch.where(keep, stat.weight, torch.zeros_like(stat.weight)))
    normal = torch.where(use_own, own.normal, stat.normal)
    color = torch.where(use_own, own.color, stat.color)
    return FlakeField(weight, normal, color, float(model.glint_sigma), len(obs) + kept)


# ----------------------------------------------------------------------------- files (docs/design.md §2.3)


def observed_json(obs: ObservedFlakes) -> dict:
    """material.json's ``observed_flakes`` entry: the count, the texture shape, the detection amplitude
    (when known) and the array file names."""
    out = {"count": len(obs), "shape": list(obs.shape), "files": {k: ARRAYS[k] for k in obs.arrays()}}
    if obs.detect_amp is not None:
        out["detect_amp"] = obs.detect_amp
    return out


def save_observed(obs: ObservedFlakes, root) -> None:
    """Write the arrays of ``obs`` as .npy files (float32) into the directory ``root``."""
    from pathlib import Path

    import numpy as np

    for name, v in obs.arrays().items():
        np.save(Path(root) / ARRAYS[name], np.ascontiguousarray(v.detach().cpu().float().numpy()))


def load_observed(root, entry: dict | None) -> ObservedFlakes | None:
    """Read the observed flakes named by material.json's ``observed_flakes`` entry (None → None)."""
    from pathlib import Path

    import numpy as np

    if not entry:
        return None
    if not isinstance(entry, dict) or not isinstance(entry.get("files"), dict) or "shape" not in entry:
        raise MaterialError(f"observed_flakes: expected {{'count', 'shape', 'files'}}, found {entry!r}")
    arrays = {}
    for name, fname in entry["files"].items():
        if name not in ARRAYS:
            raise MaterialError(f"observed_flakes: expected arrays among {sorted(ARRAYS)}, found {name!r}")
        f = Path(root) / str(fname)
        if not f.is_file():
            raise MaterialError(f"{f}: expected the observed flakes' {name} array file, found nothing")
        try:
            arrays[name] = torch.from_numpy(np.load(f, allow_pickle=False).astype(np.float32))
        except (OSError, ValueError) as e:
            raise MaterialError(f"{f}: expected a numpy .npy file, found unreadable data ({e})") from None
    missing = sorted(set(ARRAYS) - {"density"} - set(arrays))
    if missing:
        raise MaterialError(f"observed_flakes: expected arrays {missing}, found them missing")
    try:
        return ObservedFlakes(shape=tuple(entry["shape"]), detect_amp=entry.get("detect_amp"), **arrays)
    except (TypeError, ValueError) as e:
        raise MaterialError(f"observed_flakes: expected (H, W) shape, found {entry.get('shape')!r} ({e})") from None
