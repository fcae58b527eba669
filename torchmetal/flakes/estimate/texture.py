"""The diffuse texture under detected flakes.

The per-pixel least-squares texture averages a flake's glints into d(p): a pixel that glints in
one shot of N gets d raised by about glint/N, and the residual photo − Phong then understates
the glint there and turns negative in every other shot. Flake statistics fitted to that
residual come out too sparse in amplitude and too wide in spread.

:func:`texture_without_glints` re-solves d(p) at every pixel covered by a detection (dilated by
one pixel), given the fitted specular and using only the shots where that pixel was not detected:

    d(p) = Σ_k w_k a_k (I_k − S_k) / Σ_k w_k a_k²,   a_k = E_k·max(n·l, 0),

with S_k the fitted specular term and w_k = 0 for saturated, masked-out, shadowed and detected
observations and for those more than 2.5 robust σ above the median of the others (a glint below
the detection threshold), capped by the all-shot texture (glints only add light). Pixels
detected in every shot take the mean of their undetected neighbours. Every other pixel keeps
its texture, so a flake-free capture is unchanged wherever nothing was detected.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.checks import check_shape
from torchmetal.flakes.model.filters import box_mean, max_filter
from torchmetal.geometry import direction_to, dot, surface_points

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

_FILL_RADII = (2, 4, 8, 16)  # neighbourhoods tried for pixels with no undetected shot


def grown_detections(labels: Tensor) -> Tensor:
    """(N, 1, H, W) bool: the pixels of detections ``labels`` (N, H, W) (> 0 on a particle), grown by 1 px."""
    return max_filter((labels > 0).unsqueeze(1).float(), 1) > 0


def glint_energy_share(capture: Capture, phong_images: Tensor, labels: Tensor) -> float:
    """Share of a fit's squared residual (photo − ``phong_images`` (N, 3, H, W), mask pixels, unsaturated
    observations, channels summed) on the detections ``labels`` (N, H, W), grown by 1 px as
    :func:`grown_detections`: how much the glints can weigh in a least-squares fit. 0 without residual."""
    n, _, h, w = capture.images.shape
    check_shape(phong_images, (n, 3, h, w), "phong_images")
    check_shape(labels, (n, h, w), "labels")
    mask = capture.mask.reshape(1, h, w)
    on = total = 0.0
    for k in range(n):  # a shot at a time: no (N, 3, H, W) temporary
        r = capture.images[k].float() - phong_images[k].float()
        ok = mask & ~capture.saturated[k] if capture.saturated is not None else mask.expand(3, h, w)
        e = torch.where(ok, r * r, torch.zeros_like(r)).sum(0)  # (H, W)
        total += float(e.sum(dtype=torch.float64))
        on += float(e[grown_detections(labels[k : k + 1])[0, 0]].sum(dtype=torch.float64))
    return on / total if total > 0 else 0.0


def texture_without_glints(
    capture: Capture, texture: Tensor, phong_images: Tensor, labels: Tensor, *, chunk: int = 4, guard: bool = True,
    gains: dict | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Re-solve the texture under detected flakes and update the Phong renders to match.

    Args:
        capture: the :class:`~torchmetal.io.capture.Capture` the texture was fitted to.
        texture: (3, H, W) fitted texture d(p).
        phong_images: (N, 3, H, W) Phong renders of every shot with ``texture``.
        labels: (N, H, W) detection labels (> 0 on a detected particle), e.g.
            :attr:`~torchmetal.flakes.estimate.detect.Detection.labels`.
        chunk: shots processed at once.
        guard: leave out shots > 2.5 robust σ above the median and cap by ``texture`` (the
            statistics' texture: no sub-threshold glint may weaken a detected one). False gives
            the plain least-squares re-solve, unbiased where a detection was only noise (the
            material's coating).

    Returns:
        (texture (3, H, W), phong_images (N, 3, H, W), changed (1, H, W) bool): the new texture,
        the renders with it, and the pixels whose texture was re-solved.
    """
    n, _, h, w = capture.images.shape
    check_shape(texture, (3, h, w), "texture")
    check_shape(phong_images, (n, 3, h, w), "phong_images")
    check_shape(labels, (n, h, w), "labels")
    flagged = grown_detections(labels)
    changed = flagged.any(0)  # (1, H, W)
    if not bool(changed.any()):
        return texture, phong_images, changed
    dt = texture.dtype
    idx = torch.nonzero(changed[0].flatten(), as_tuple=True)[0]  # (M,) pixels to re-solve
    shots = [slice(k0, min(n, k0 + chunk)) for k0 in range(0, n, chunk)]
    est, gain, a_idx = _clean_estimates(capture, texture, phong_images, flagged, idx, shots, gains)
    # a glint below the detection threshold in a few clean shots (those next to the detected
    # ones) would raise the mean, and with it lower every detected glint's amplitude: shots
    # more than 2.5 robust σ above the median are left out of the weighted mean
    med = torch.nanquantile(est, 0.5, dim=0)  # (3, M)
    mad = 1.4826 * torch.nanquantile((est - med).abs(), 0.5, dim=0)
    keep = (gain > 0) & ~(est > med + 2.5 * mad + 1e-6) if guard else gain > 0
    wk = torch.where(keep, gain * gain, torch.zeros_like(gain))
    num = (wk * torch.nan_to_num(est)).sum(0)
    den = wk.sum(0)
    solved = torch.zeros(3, h * w, dtype=torch.bool, device=texture.device)
    solved[:, idx] = den > 0
    solved = solved.view(3, h, w)
    d = torch.zeros(3, h * w, dtype=dt, device=texture.device)
    d[:, idx] = num / den.clamp_min(1e-30)
    # glints only add light: the clean solve never exceeds the all-shot one (noise of few shots)
    d = d.view(3, h, w)
    d = torch.where(solved, torch.minimum(d, texture) if guard else d, torch.zeros_like(texture))
    filled = _fill_unsolved(torch.where(changed, d, texture), changed, solved)
    new = torch.where(changed, filled.clamp_min(0.0), texture)
    delta = new - texture  # 0 off the re-solved pixels: the renders change only there
    phong = phong_images.to(torch.promote_types(phong_images.dtype, dt), copy=True)
    flat = phong.view(n, 3, h * w)
    flat[:, :, idx] = flat[:, :, idx] + delta.reshape(1, 3, h * w)[:, :, idx] * a_idx
    return new, phong, changed


def _clean_estimates(capture: Capture, texture: Tensor, phong_images: Tensor, flagged: Tensor, idx: Tensor,
                     shots: list[slice], gains: dict | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Per shot, the texture each pixel ``idx`` (M,) implies (N, 3, M) (NaN where the shot is not usable
    there: masked, saturated, shadowed or detected), its diffuse gain a (N, 3, M) (0 there) and a itself
    (``gains``: :func:`texture_without_glints`)."""
    n = capture.images.shape[0]
    dt = texture.dtype
    valid = capture.mask.unsqueeze(0) & ~capture.saturated
    est = torch.empty(n, 3, idx.numel(), dtype=dt, device=texture.device)
    gain = torch.empty_like(est)
    a_idx = torch.empty_like(est)
    for sl in shots:
        key = (sl.start, sl.stop, dt)
        a = _diffuse_gain(capture, sl, dt) if gains is None or key not in gains else gains[key]
        if gains is not None:
            gains[key] = a
        a_idx[sl] = a.flatten(2)[:, :, idx]
        spec = phong_images[sl] - texture * a
        ok = valid[sl] & ~flagged[sl] & (a > 0)
        e = (capture.images[sl].to(dt) - spec) / a.clamp_min(1e-12)
        est[sl] = torch.where(ok, e, torch.full_like(e, float("nan"))).flatten(2)[:, :, idx]
        gain[sl] = torch.where(ok, a, torch.zeros_like(a)).flatten(2)[:, :, idx]
    return est, gain, a_idx


def _fill_unsolved(base: Tensor, changed: Tensor, solved: Tensor) -> Tensor:
    """``base`` (3, H, W) with the pixels detected in every shot (changed, not solved) filled by the mean of
    their solved/untouched neighbours (widening neighbourhoods, :data:`_FILL_RADII`)."""
    known = (~changed | solved.all(0, keepdim=True)).to(base.dtype)  # (1, H, W)
    filled = base
    for r in _FILL_RADII:
        missing = known == 0
        if not bool(missing.any()):
            break
        mean = box_mean((base * known).unsqueeze(0), r, known.unsqueeze(0))[0]
        got = box_mean(known.unsqueeze(0), r)[0] > 0
        filled = torch.where(missing & got, mean, filled)
        known = torch.where(missing & got, torch.ones_like(known), known)
        base = filled
    return filled


def _diffuse_gain(capture: Capture, shots: slice, dtype: torch.dtype) -> Tensor:
    """a = E·max(n·l, 0) of the shots ``shots``, (B, 3, H, W): the diffuse term per unit texture (the
    light's direction and distance only: the same values as :func:`~torchmetal.geometry.shading_geometry`'s
    ``irradiance · n_dot_l``, at half its cost)."""
    n = capture.normals.to(dtype)
    points = surface_points(n.shape[-2], n.shape[-1], capture.size, dtype=dtype, device=n.device)
    l, dist2 = direction_to(points, capture.lights[shots].to(dtype))
    a = capture.intensities[shots].to(dtype)[:, :, None, None] / dist2 * dot(n.unsqueeze(0), l).clamp_min(0.0)
    return a.expand(-1, 3, -1, -1)
