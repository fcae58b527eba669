"""The report's panels: display scaling and one matplotlib ``Axes`` at a time (:mod:`torchmetal.report`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from torchmetal.geometry import shading_geometry, surface_points
from torchmetal.io.images import linear_to_srgb
from torchmetal.metrics import psnr

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.image import AxesImage

    from torchmetal.flakes.estimate.results import Particles
    from torchmetal.io.capture import Capture


# capture fields, with defaults for a bare object


def _size(capture) -> tuple[float, float]:
    size = getattr(capture, "size", None)
    if size is None:
        return (1.0, 1.0)
    return (float(size[0]), float(size[1]))


def _normals(capture) -> Tensor:
    n = getattr(capture, "normals", None)
    if n is not None:
        return n.float()
    _, _, h, w = capture.images.shape
    n = torch.zeros(3, h, w)
    n[2] = 1.0
    return n


def _mask(capture) -> Tensor | None:
    m = getattr(capture, "mask", None)
    if m is None:
        return None
    m = torch.as_tensor(m).bool()
    return m.reshape(m.shape[-2:]) if m.dim() > 2 else m


# ---------------------------------------------------------------------------------------------
# display


def _chw(img: Tensor | np.ndarray) -> Tensor:
    x = torch.as_tensor(np.asarray(img) if not isinstance(img, Tensor) else img).detach().float().cpu()
    if x.dim() == 4:
        if x.shape[0] != 1:
            raise ValueError(f"expected one image (3, H, W), found a batch {tuple(x.shape)}")
        x = x[0]
    if x.dim() == 2:
        x = x.unsqueeze(0).expand(3, -1, -1)
    if x.dim() == 3 and x.shape[0] not in (1, 3) and x.shape[-1] in (1, 3):
        x = x.permute(2, 0, 1)
    if x.shape[0] == 1:
        x = x.expand(3, -1, -1)
    return x


def exposure_for(img: Tensor, percentile: float = 99.5) -> float:
    """Scale that maps the ``percentile`` of a linear image's luminance-ish max channel to 1."""
    x = _chw(img).amax(0).flatten()
    v = float(torch.quantile(x[:: max(1, x.numel() // 200_000)], percentile / 100.0))
    return 1.0 / v if v > 0 and math.isfinite(v) else 1.0


def to_display(img: Tensor | np.ndarray, exposure: float | None = None) -> np.ndarray:
    """Linear RGB image → (H, W, 3) float array in [0, 1], sRGB-encoded for viewing.

    Args:
        img: (3, H, W), (1, 3, H, W), (H, W, 3) or (H, W) linear values.
        exposure: multiply before encoding; default from :func:`exposure_for`.
    """
    x = _chw(img)
    k = exposure_for(x) if exposure is None else exposure
    return linear_to_srgb((x * k).clamp(0.0, 1.0)).permute(1, 2, 0).numpy()


def _off(ax) -> None:
    ax.set_xticks([])
    ax.set_yticks([])


def plot_image(ax: Axes, img: Tensor, title: str = "", *, exposure: float | None = None) -> None:
    """Show one linear image on ``ax`` (sRGB display, shared ``exposure`` when given)."""
    ax.imshow(to_display(img, exposure), interpolation="nearest")
    ax.set_title(title, fontsize=9)
    _off(ax)


def plot_shots(axes: Axes | Sequence[Axes] | np.ndarray, images: Tensor, *, indices: Sequence[int] | None = None,
               exposure: float | None = None, labels: Sequence[str] | None = None) -> float:
    """Show photos ``images[indices]`` (N, 3, H, W) on ``axes`` with one shared exposure.

    Returns:
        the exposure used (pass it on so renders are shown on the same scale).
    """
    axes = list(np.ravel(axes))
    idx = list(indices) if indices is not None else list(range(min(len(axes), images.shape[0])))
    if exposure is None:
        exposure = min(exposure_for(images[i]) for i in idx)
    for n, (ax, i) in enumerate(zip(axes, idx)):
        plot_image(ax, images[i], labels[n] if labels is not None else f"shot {i}", exposure=exposure)
    for ax in axes[len(idx) :]:
        ax.axis("off")
    return exposure


def lobe_samples(
    capture: Capture, texture: Tensor, *, max_samples: int = 4000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Evidence for the specular lobe: per lit pixel and shot, the angle between r and v and the
    specular residual (photo − d·max(n·l, 0)·E)/E per channel.

    Geometry is computed only at the sampled pixels (cheap at any image size).

    Returns:
        angles in degrees (M,), residuals (M, 3); M ≤ ``max_samples``: half drawn uniformly among
        the pixels of every shot, half among those within 5° of the mirror direction (the few that
        pin down the lobe's peak); unlit, masked and saturated observations are dropped.
    """
    g = torch.Generator().manual_seed(seed)
    n_shots, _, h, w = capture.images.shape
    normals = _normals(capture).reshape(3, 1, h * w)
    points = surface_points(h, w, _size(capture), dtype=normals.dtype).reshape(3, 1, h * w)
    mask = _mask(capture)
    sat = getattr(capture, "saturated", None)
    per_shot = max(2, max_samples // n_shots)
    texture = texture.detach().reshape(3, h * w).to(normals.dtype)
    angles, values = [], []
    for k in range(n_shots):
        sl = slice(k, k + 1)
        lights, inten, cams = capture.lights[sl].to(normals.dtype), capture.intensities[sl].to(normals.dtype), capture.cameras[sl].to(normals.dtype)
        # candidates: a uniform draw, plus pixels near the mirror direction (found on a coarse grid)
        uni = torch.randint(0, h * w, (4 * per_shot,), generator=g)
        step = max(1, int(math.sqrt(h * w / 20000)))
        grid = (torch.arange(0, h, step).view(-1, 1) * w + torch.arange(0, w, step).view(1, -1)).flatten()
        gq = shading_geometry(normals[:, :, grid], lights, inten, cams, points=points[:, :, grid])
        near = grid[(gq.r_dot_v[0, 0, 0] > math.cos(math.radians(5.0))) & (gq.n_dot_l[0, 0, 0] > 0)]
        if near.numel() > 2 * per_shot:
            near = near[torch.randperm(near.numel(), generator=g)[: 2 * per_shot]]
        idx = torch.cat([uni, near])
        geom = shading_geometry(normals[:, :, idx], lights, inten, cams, points=points[:, :, idx])
        nl = geom.n_dot_l[0, 0, 0]
        e = geom.irradiance[0, :, 0]
        photo = capture.images[k].reshape(3, h * w)[:, idx].to(normals.dtype)
        resid = (photo - texture[:, idx] * nl.clamp_min(0) * e) / e.clamp_min(1e-12)
        ok = nl > 0.05
        if mask is not None:
            ok &= mask.reshape(-1)[idx]
        if isinstance(sat, Tensor) and sat.dim() == 4:
            ok &= ~sat[k].reshape(-1, h * w)[:, idx].any(0)
        ok_u = ok.clone()
        ok_u[uni.numel():] = False
        ok_n = ok & ~ok_u
        ok_n[: uni.numel()] = False
        keep = torch.cat([ok_u.nonzero().flatten()[: per_shot // 2 + 1], ok_n.nonzero().flatten()[: per_shot - per_shot // 2]])
        rv = geom.r_dot_v[0, 0, 0].clamp(-1, 1)
        angles.append(torch.rad2deg(torch.acos(rv[keep])))
        values.append(resid[:, keep].T)
    if not angles:
        return np.zeros(0), np.zeros((0, 3))
    return torch.cat(angles).double().numpy(), torch.cat(values).double().numpy()


_RGB = ("#d62728", "#2ca02c", "#1f77b4")


def plot_lobe(
    ax: Axes,
    s: Tensor,
    alpha: Tensor,
    *,
    truth: tuple[Tensor, Tensor] | None = None,
    samples: tuple[np.ndarray, np.ndarray] | None = None,
    max_angle: float | None = None,
) -> None:
    """Specular lobe s_c·cos(θ)^α_c against θ = angle(r, v) in degrees, per channel.

    Args:
        s, alpha: (3,) fitted global terms (or per-cluster means).
        truth: optional (s, alpha) drawn dashed.
        samples: optional (angles (M,), residuals (M, 3)) from :func:`lobe_samples`, drawn as dots.
        max_angle: x-axis limit; default where the widest lobe falls to 1 % of its peak.
    """
    s = torch.as_tensor(s).double().cpu()
    a = torch.as_tensor(alpha).double().cpu()
    if max_angle is None:
        # cos(θ)^α = 0.01 → θ = acos(0.01^(1/α)); show 1.5× that, at least 5°
        amin = float(a.clamp_min(1.0).min())
        max_angle = max(5.0, min(90.0, 1.5 * math.degrees(math.acos(0.01 ** (1.0 / amin)))))
    th = torch.linspace(0.0, max_angle, 400, dtype=torch.float64)
    c = torch.cos(torch.deg2rad(th)).clamp_min(0)
    if samples is not None and len(samples[0]):
        ang, val = samples
        keep = ang <= max_angle
        for ch in range(3):
            ax.scatter(ang[keep], val[keep, ch], s=4, color=_RGB[ch], alpha=0.3, linewidths=0, rasterized=True)
    for ch in range(3):
        ax.plot(th.numpy(), (s[ch] * c ** a[ch]).numpy(), color=_RGB[ch], lw=1.4, alpha=0.9,
                label=f"{'RGB'[ch]}: s={float(s[ch]):.3g}, α={float(a[ch]):.3g}")
    if truth is not None:
        ts = torch.as_tensor(truth[0]).double().cpu()
        ta = torch.as_tensor(truth[1]).double().cpu()
        for ch in range(3):
            ax.plot(th.numpy(), (ts[ch] * c ** ta[ch]).numpy(), color="k", lw=0.8, ls="--",
                    label="truth" if ch == 0 else None)
    top = float((s.max() if truth is None else max(s.max(), torch.as_tensor(truth[0]).max())))
    ax.set_ylim(-0.1 * top, 1.25 * top)
    ax.set_xlim(0, max_angle)
    ax.set_xlabel("angle between r and v (°)", fontsize=8)
    ax.set_ylabel("specular / irradiance", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=6, loc="upper right")


def particle_ellipses(particles: Particles | None, shot: int | None = None) -> list[tuple[float, float, float, float, float]]:
    """Detected particles as ellipses ``(x, y, width, height, angle_deg)``: x = column and
    y = row of the centroid (pixel centres at integers, as ``imshow`` draws them), full axis
    lengths, angle in degrees from +column towards up (counter-clockwise on screen).

    Args:
        particles: a :class:`~torchmetal.flakes.estimate.results.Particles` table (fields ``shot``,
            ``cy``, ``cx``, ``major``, ``minor``, ``angle``) or None.
        shot: keep only the particles of this shot.
    """
    if particles is None or len(particles) == 0:
        return []
    keep = torch.ones(len(particles), dtype=torch.bool)
    if shot is not None:
        keep = particles.shot.cpu() == shot
    cols = [getattr(particles, k).detach().cpu().double()[keep].tolist() for k in ("cx", "cy", "major", "minor", "angle")]
    return [(x, y, w, h, math.degrees(a)) for x, y, w, h, a in zip(*cols)]


def plot_flakes(ax: Axes, residual: Tensor, particles: Particles | None = None, *, shot: int | None = None, title: str | None = None,
                window: tuple[int, int, int, int] | None = None, color: str = "#00e5ff",
                max_ellipses: int = 5000) -> int:
    """Flake residual (photo − Phong render) of one shot with detected ellipses drawn on it.

    Args:
        residual: (3, H, W) linear residual; negative values show black.
        particles: :class:`~torchmetal.flakes.estimate.results.Particles` or None; shot: draw this shot's.
        window: optional (row0, row1, col0, col1) to zoom into (the exposure still comes from the
            whole residual).

    Returns:
        the number of ellipses of the shot (drawn, or clipped away by ``window``).
    """
    from matplotlib.patches import Ellipse

    r = _chw(residual).clamp_min(0)
    ax.imshow(to_display(r, exposure_for(r, 99.9)), interpolation="nearest")
    ells = particle_ellipses(particles, shot)
    for x, y, w, h, ang in ells[:max_ellipses]:
        # image y grows downwards: a counter-clockwise angle in the surface frame is clockwise on screen
        ax.add_patch(Ellipse((x, y), max(w, 1.5) + 2, max(h, 1.5) + 2, angle=-ang,
                             fill=False, ec=color, lw=0.7))
    if window is not None:
        r0, r1, c0, c1 = window
        ax.set_xlim(c0 - 0.5, c1 - 0.5)
        ax.set_ylim(r1 - 0.5, r0 - 0.5)
    ax.set_title(title if title is not None else f"detected flakes ({len(ells)} in this shot)", fontsize=9)
    _off(ax)
    return len(ells)


def plot_error(ax: Axes, pred: Tensor, ref: Tensor, *, valid: Tensor | None = None, title: str | None = None,
               vmax: float | None = None, fig: Figure | None = None) -> AxesImage:
    """Per-pixel |pred − ref| (max over channels) in percent of the reference's peak, as a heat map.

    Args:
        valid: optional (H, W) bool; other pixels (e.g. saturated in the photo) are drawn cyan and
            left out of the PSNR in the default title.
    """
    from matplotlib.ticker import FormatStrFormatter

    p, r = _chw(pred), _chw(ref)
    err = 100.0 * (p - r).abs().amax(0) / float(r.max().clamp_min(1e-12))  # percent of the peak
    ok = torch.ones_like(err, dtype=torch.bool) if valid is None else torch.as_tensor(valid).bool().reshape(err.shape)
    shown = err[ok]
    if vmax is None:
        vmax = float(torch.quantile(shown[:: max(1, shown.numel() // 200_000)], 0.999)) if shown.numel() else 1.0
    import matplotlib

    cmap = matplotlib.colormaps["magma"].with_extremes(bad="#00e5ff")
    im = ax.imshow(np.ma.masked_array(err.numpy(), mask=~ok.numpy()), cmap=cmap, vmin=0.0, vmax=max(vmax, 1e-9),
                   interpolation="nearest")
    if title is None:
        title = f"|render − photo|, % of peak (PSNR {psnr(p, r, mask=ok.expand_as(r)):.1f} dB)"
        if not bool(ok.all()):
            title += "\ncyan: saturated in the photo, left out"
    ax.set_title(title, fontsize=9)
    _off(ax)
    if fig is not None:
        cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02, format=FormatStrFormatter("%.2g%%"))
        cb.ax.tick_params(labelsize=6)
    return im
