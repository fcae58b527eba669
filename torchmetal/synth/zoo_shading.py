"""The scene zoo's numpy shading: the surface's pixel centres, directions to lights and cameras, and the
truth lobes (:mod:`torchmetal.synth.zoo_render`'s module docstring). No torchmetal geometry or lobe code."""

from __future__ import annotations

import math

import numpy as np

WIDTH = 0.1  # surface size, metres (square)


def surface_points(n: int) -> np.ndarray:
    """(3, n, n) docs/design.md §2.1 pixel centres on the z = 0 plane."""
    j = (np.arange(n) + 0.5) / n - 0.5
    x = np.broadcast_to(j[None, :] * WIDTH, (n, n))
    y = np.broadcast_to(-j[:, None] * WIDTH, (n, n))
    return np.stack([x, y, np.zeros((n, n))])


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=0, keepdims=True)


def sph(elev: float, azim: float) -> np.ndarray:
    e, a = math.radians(elev), math.radians(azim)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def towards(points: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction (3, n, n) from the points to a homogeneous target, and the squared distance."""
    if target[3] == 0:
        d = unit(target[:3].reshape(3, 1, 1) * np.ones_like(points))
        return d, np.ones(points.shape[1:])
    v = target[:3].reshape(3, 1, 1) - points
    d2 = (v * v).sum(0)
    return v / np.sqrt(d2), d2


def lobe_value(kind: str, n: np.ndarray, l: np.ndarray, v: np.ndarray, s: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """(3, n, n) specular factor per unit irradiance; s, alpha (3,) or (3, n, n)."""
    s = s.reshape(3, 1, 1) if s.ndim == 1 else s
    alpha = alpha.reshape(3, 1, 1) if alpha.ndim == 1 else alpha
    nl = (n * l).sum(0)
    lit = (nl > 0)[None]
    if kind == "phong":
        r = 2 * nl[None] * n - l
        c = np.clip((r * v).sum(0), 0.0, 1.0)[None]
        f = np.power(c, alpha)
    else:
        h = unit(l + v)
        c = np.clip((n * h).sum(0), 0.0, 1.0)[None]
        if kind == "blinn":
            f = np.power(c, 4.0 * alpha)
        else:
            a2 = 2.0 / (alpha + 2.0)
            f = (a2 / ((c * c) * (a2 - 1.0) + 1.0) ** 2) * a2  # D / D(0) with D(0) = 1/(π a²)
            if kind == "ggx_full":  # × Schlick's F/F0 (F0 0.04) × G₁(n·l)·G₁(n·v)/(n·v), Smith–GGX: 0 where n·v ≤ 0
                nv = (n * v).sum(0)[None]
                x = np.clip(1.0 - (v * h).sum(0)[None], 0.0, 1.0)
                fres = 1.0 + (1.0 / 0.04 - 1.0) * x**5
                nl1, nv1 = np.clip(nl[None], 0.0, 1.0), np.clip(nv, 1e-12, 1.0)
                g1 = lambda t: 2.0 * t / (t + np.sqrt(a2 + (1.0 - a2) * t * t))  # noqa: E731
                f = np.where(nv > 0, f * fres * g1(nl1) * g1(nv1) / nv1, 0.0)
    return np.where(lit, s * f, 0.0)
