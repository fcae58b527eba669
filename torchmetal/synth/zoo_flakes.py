"""The scene zoo's flakes: elliptical discs (Poisson positions, log-normal area, uniform orientation,
Rayleigh tilt about the surface normal), their pixel coverage and their Gaussian glints — numpy, independent
of the project's hash field (:mod:`torchmetal.synth.zoo_render`)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from torchmetal.synth.zoo_shading import unit

if TYPE_CHECKING:
    from torchmetal.synth.zoo_render import Truth


def make_flakes(spec: dict, n: int, rng: np.random.Generator) -> dict:
    """Flake discs: centres (F, 2) px (x right, y down), semi-axes (F, 2), angle (F,), normal (F, 3), colour (F, 3)."""
    count = rng.poisson(spec["density"] * n * n)
    area = spec["area_median"] * np.exp(spec.get("area_log_std", 0.35) * rng.normal(size=count))
    lo, hi = spec.get("aspect", (0.5, 1.0))
    aspect = rng.uniform(lo, hi, count)  # minor / major
    major = np.sqrt(area / (math.pi * aspect))
    theta = spec["tilt_sigma"] * np.sqrt(-2.0 * np.log(1.0 - rng.random(count)))  # Rayleigh
    phi = rng.uniform(0, 2 * math.pi, count)
    normal = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    color = np.asarray(spec.get("color", (0.9, 0.8, 0.6)))[None] * np.exp(0.1 * rng.normal(size=(count, 3)))
    out = {"centre": rng.uniform(0, n, (count, 2)), "axes": np.stack([major, major * aspect], -1),
           "angle": rng.uniform(0, math.pi, count), "normal": normal, "color": color, "area": area}
    region = spec.get("region")
    if region is None:
        return out
    if region != "left":
        raise ValueError(f"flakes region: expected None or 'left', found {region!r}")
    keep = out["centre"][:, 0] < 0.5 * n  # glitter on the left half only (x < 0): the same draws, thinned
    return {k: v[keep] for k, v in out.items()}


def flake_cover(fl: dict, n: int, sub: int = 4) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per flake: pixel rows, cols and fractional coverage (sub×sub supersampling)."""
    out = []
    offs = (np.arange(sub) + 0.5) / sub
    for (cx, cy), (a, b), ang in zip(fl["centre"], fl["axes"], fl["angle"]):
        r = int(math.ceil(a)) + 1
        x0, x1 = max(0, int(cx) - r), min(n, int(cx) + r + 1)
        y0, y1 = max(0, int(cy) - r), min(n, int(cy) + r + 1)
        if x0 >= x1 or y0 >= y1:
            out.append((np.zeros(0, int), np.zeros(0, int), np.zeros(0)))
            continue
        ys = (np.arange(y0, y1)[:, None] + offs[None]).reshape(-1)
        xs = (np.arange(x0, x1)[:, None] + offs[None]).reshape(-1)
        dx, dy = xs[None, :] - cx, ys[:, None] - cy
        ca, sa = math.cos(ang), math.sin(ang)
        u, w = dx * ca + dy * sa, -dx * sa + dy * ca
        inside = ((u / a) ** 2 + (w / b) ** 2 <= 1.0).astype(np.float64)
        cov = inside.reshape(y1 - y0, sub, x1 - x0, sub).mean((1, 3))
        rr, cc = np.nonzero(cov)
        out.append((rr + y0, cc + x0, cov[rr, cc]))
    return out


def centre_pixels(fl: dict, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(F,) row and column of the pixel under each flake's centre."""
    return (np.clip(fl["centre"][:, 1].astype(int), 0, n - 1), np.clip(fl["centre"][:, 0].astype(int), 0, n - 1))


def flake_normals(truth: Truth) -> np.ndarray:
    """(3, F) flake normals in the world: each flake's tilt applied around the surface normal under it."""
    fl = truth.flakes
    cy, cx = centre_pixels(fl, truth.texture.shape[-1])
    base = truth.normals[:, cy, cx]  # (3, F)
    helper = np.where(np.abs(base[0:1]) < 0.9, np.array([[1.0], [0.0], [0.0]]), np.array([[0.0], [1.0], [0.0]]))
    t1 = unit(helper - (helper * base).sum(0, keepdims=True) * base)  # x on a flat sample
    t2 = np.cross(base.T, t1.T).T  # y on a flat sample
    local = fl["normal"].T  # (3, F) in the frame (t1, t2, n)
    return unit(local[0:1] * t1 + local[1:2] * t2 + local[2:3] * base)


def flake_glints(truth: Truth, l: np.ndarray, v: np.ndarray, e: np.ndarray) -> np.ndarray:
    """(3, n, n) the flakes' glints in one shot: directions to the light ``l`` and camera ``v`` (3, n, n), irradiance ``e``."""
    fl, spec = truth.flakes, truth.flakes["spec"]
    n = truth.texture.shape[-1]
    e = np.broadcast_to(e, (3, n, n))  # a directional light's irradiance is (3, 1, 1): indexed per pixel below
    out = np.zeros((3, n, n))
    cy, cx = centre_pixels(fl, n)
    h = unit(l[:, cy, cx] + v[:, cy, cx])  # (3, F) half vector at each flake
    cosang = np.clip((fl["world_normal"] * h).sum(0), -1.0, 1.0)
    amp = np.exp(-np.arccos(cosang) ** 2 / (2 * spec["glint_sigma"] ** 2))  # (F,)
    lit = (l[2, cy, cx] > 0) & (v[2, cy, cx] > 0)
    for f, (rr, cc, cov) in enumerate(truth.cover):
        if amp[f] < 1e-6 or not lit[f] or rr.size == 0:
            continue
        out[:, rr, cc] += (amp[f] * cov)[None] * fl["color"][f][:, None] * e[:, rr, cc]
    return out


def flake_pixels(truth: Truth) -> np.ndarray:
    """(n, n) bool: the pixels any flake covers, grown by one pixel."""
    n = truth.texture.shape[-1]
    m = np.zeros((n, n), bool)
    for rr, cc, _ in truth.cover or []:
        m[rr, cc] = True
    if truth.cover:
        g = m.copy()
        g[1:] |= m[:-1]
        g[:-1] |= m[1:]
        g[:, 1:] |= g[:, :-1].copy()
        g[:, :-1] |= g[:, 1:].copy()
        m = g
    return m
