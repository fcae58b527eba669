"""``lobe="auto"``: pick the specular lobe (phong, blinn, ggx) on shots left out of the fit.

On the selection subsample (the same strided pixel grid as the cluster choice), a global Phong
fit on all shots ranks the shots by predicted specular energy; the ``holds`` most telling ones
(every shot, up to 12) are left out in turn. For each candidate lobe and each left-out shot: a coarse α grid, then the
variable-projection LM (:func:`~torchmetal.fit.refine.fit_specular`) on the other shots, and the
squared errors of rendering the left-out shot's valid observations.

Phong — docs/design.md §2.2's model — is kept unless another lobe's errors are lower *beyond noise*: the
held-out MSE is mostly the photo's own noise (on the zoo's blinn scene, Blinn is 1.2 dB closer to the
clean truth than Phong but only 0.1 % lower in held-out MSE, leave-one-out over its 10 shots), so a relative-gain rule cannot see
the lobe. The errors of two lobes pair up observation by observation (same pixels, same noise), and
the paired difference's mean over its standard error (z) measures the gain against that noise; a lobe
replaces Phong when z > ``z_min`` and its MSE is lower by at least ``min_gain``. So a Phong-like sample
keeps the paper's lobe.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchmetal.fit.clusters import evidence
from torchmetal.fit.lobes import lobe_factor
from torchmetal.fit.problem import Observations, build_observations
from torchmetal.fit.refine import SpecFit, fit_specular, grid_beta, texture_map
from torchmetal.lobes import LOBES

__all__ = ["LobeSelection", "choose_lobe", "LOBE_GRID", "MIN_GAIN", "HOLDS"]

LOBE_GRID = tuple(float(2**i) for i in range(14))  # α = 1 … 8192, ×2 steps: every lobe starts near its optimum
MIN_GAIN = 5e-4  # another lobe must lower the held-out MSE by 0.05 % …
Z_MIN = 4.0  # … and by more than 4 standard errors of the paired difference
HOLDS = 12  # shots left out in turn (the ones with most predicted specular energy): every shot of most captures


@dataclass
class LobeSelection:
    """Outcome of the held-out comparison: the chosen lobe and the evidence."""

    lobe: str
    holds: list[int] = field(default_factory=list)
    mse: dict = field(default_factory=dict)  # lobe → mean held-out MSE over ``holds``
    z: dict = field(default_factory=dict)  # lobe → paired z of its gain over phong (> 0: lower errors)
    alpha: dict = field(default_factory=dict)  # lobe → fitted α (3,) on the first fold
    reason: str = ""

    def to_dict(self) -> dict:
        psnr = {k: (10.0 * math.log10(1.0 / v) if v > 0 else math.inf) for k, v in self.mse.items()}
        return {"lobe": self.lobe, "holds": list(self.holds), "mse": dict(self.mse), "psnr_heldout": psnr,
                "z": dict(self.z), "alpha": dict(self.alpha), "reason": self.reason}


def fit_lobe(obs: Observations, *, tol: float, max_iters: int, grid: tuple[float, ...] = LOBE_GRID) -> SpecFit:
    """Global specular fit of ``obs``'s lobe: best α of ``grid``, then the LM."""
    return fit_specular(obs, grid_beta(obs, 1, grid=grid), tol=tol, max_iters=max_iters)


def specular_energy(obs: Observations, fit: SpecFit) -> Tensor:
    """(N,) float64 Σ w·(s·b)² per shot: how much of each shot the specular term predicts."""
    s3, a3 = fit.s[0].to(obs.dtype).view(1, 3, 1), fit.alpha[0].to(obs.dtype).view(1, 3, 1)
    energy = torch.zeros(obs.num_shots, dtype=torch.float64, device=obs.device)
    for j in range(len(obs.chunks)):
        y, g, u, L, w, inten = obs.chunk(j)
        b = s3 * inten * u * lobe_factor(L, a3, obs.geo_chunk(j), obs.lobe)
        energy += (w * b * b).sum((1, 2)).double()
    return energy


def heldout_errors(hold: Observations, texture: Tensor, s: Tensor, alpha: Tensor) -> Tensor:
    """Squared errors (M,) float64 of the valid held-out observations, in a fixed order (the valid
    set does not depend on the lobe, so two lobes' errors pair up element by element). The texture
    is clamped at 0 as the material stores it (see :func:`~torchmetal.fit.clusters.heldout_mse`)."""
    texture = texture.clamp_min(0.0)
    s3, a3 = s[0].to(hold.dtype).view(1, 3, 1), alpha[0].to(hold.dtype).view(1, 3, 1)
    out = []
    for j, (p0, p1) in enumerate(hold.chunks):
        y, g, u, L, w, inten = hold.chunk(j)
        r = y - inten * g * texture[:, p0:p1] - s3 * (inten * u) * lobe_factor(L, a3, hold.geo_chunk(j), hold.lobe)
        out.append((r * r)[w > 0].double())
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.float64)


def paired_z(err: Tensor, ref: Tensor) -> float:
    """z of the mean paired difference ref − err (> 0: ``err`` is lower), over M observations."""
    d = ref - err
    if d.numel() < 2:
        return 0.0
    sd = float(d.std())
    return float(d.mean()) / (sd / math.sqrt(d.numel())) if sd > 0 else (math.inf if float(d.mean()) > 0 else 0.0)


def choose_lobe(
    capture, *, stride: int, tol: float, max_iters: int, dtype: torch.dtype, chunk: int,
    candidates: tuple[str, ...] = LOBES, holds: int = HOLDS, min_gain: float = MIN_GAIN, z_min: float = Z_MIN,
) -> LobeSelection:
    """Fit each candidate lobe on all shots but one (in turn, ``holds`` shots) on a pixel grid of
    ``stride``; keep the lowest held-out MSE, Phong unless beaten beyond noise (module docstring)."""
    n = int(capture.images.shape[0])
    if n < 3:
        return LobeSelection("phong", reason=f"a held-out test needs >= 3 shots, found {n}: phong (docs/design.md §2.2)")
    every = build_observations(capture, stride=stride, dtype=dtype, chunk=chunk)
    base = fit_lobe(every, tol=tol, max_iters=max_iters)
    if not bool(evidence(base).any()):
        return LobeSelection("phong", reason="no highlight evidence: the lobe shape is not observable; phong (docs/design.md §2.2)")
    order = torch.argsort(specular_energy(every, base), descending=True).tolist()
    del every
    held = order[: max(1, min(holds, n))]
    sel = LobeSelection("phong", holds=held)
    errors: dict[str, Tensor] = {}
    for lobe in candidates:
        parts = []
        for i, hold in enumerate(held):
            obs = build_observations(capture, stride=stride, shots=[k for k in range(n) if k != hold], dtype=dtype,
                                     chunk=chunk, lobe=lobe)
            fit = fit_lobe(obs, tol=tol, max_iters=max_iters)
            ho = build_observations(capture, stride=stride, shots=[hold], dtype=dtype, chunk=chunk, lobe=lobe)
            parts.append(heldout_errors(ho, texture_map(obs, fit.s, fit.eb), fit.s, fit.alpha))
            if i == 0:
                sel.alpha[lobe] = [float(a) for a in fit.alpha[0]]
        errors[lobe] = torch.cat(parts)
        sel.mse[lobe] = float(errors[lobe].mean()) if errors[lobe].numel() else math.inf
    ref = "phong" if "phong" in errors else min(sel.mse, key=sel.mse.get)
    for lobe in errors:
        if lobe != ref:
            sel.z[lobe] = paired_z(errors[lobe], errors[ref])
    wins = [lb for lb in sel.z if sel.z[lb] > z_min and sel.mse[lb] < (1.0 - min_gain) * sel.mse[ref]]
    best = min(wins, key=sel.mse.get) if wins else ref
    sel.lobe = best
    others = ", ".join(f"{lb} {sel.mse[lb]:.4g} (z {sel.z[lb]:.1f})" for lb in sel.z)
    if best != ref:
        sel.reason = (f"{best} lowers the held-out MSE (shots {held}) beyond noise: {ref} {sel.mse[ref]:.4g}, {others}")
    else:
        sel.reason = (f"held-out MSE (shots {held}): {ref} {sel.mse[ref]:.4g}, {others}: no lobe lower beyond noise "
                      f"(z > {z_min:g} and {min_gain:.1%}); {ref} kept")
    return sel
