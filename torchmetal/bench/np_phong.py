"""The benchmark baselines' numpy side of a capture and of the model (no torch): a capture as numpy
arrays (:func:`capture_arrays`), the shading geometry (:func:`np_geometry`) and the Phong render
(:func:`np_render`) of docs/design.md §2.2. Re-exported by :mod:`torchmetal.bench.baselines`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, DTypeLike

    from torchmetal.io.capture import Capture

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


def capture_arrays(capture: Capture, dtype: DTypeLike = np.float32) -> dict:
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


def np_geometry(normals: np.ndarray, lights: np.ndarray, intensities: np.ndarray, cameras: np.ndarray,
                size: tuple[float, float], dtype: DTypeLike = np.float32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def np_render(texture: ArrayLike, s: ArrayLike, alpha: ArrayLike, normals: ArrayLike, light: ArrayLike,
              intensity: ArrayLike, camera: ArrayLike, size: tuple[float, float]) -> np.ndarray:
    """numpy Phong render of B shots (docs/design.md §2.2), (B, 3, H, W) float64."""
    nl, q, e = np_geometry(np.asarray(normals, np.float64), np.asarray(light, np.float64).reshape(-1, 4),
                           np.asarray(intensity, np.float64).reshape(-1, 3), np.asarray(camera, np.float64).reshape(-1, 4),
                           size, dtype=np.float64)
    s3 = np.asarray(s, np.float64).reshape(1, 3, 1, 1)
    a3 = np.asarray(alpha, np.float64).reshape(1, 3, 1, 1)
    spec = np.where(nl > 0, s3 * _lobe(q, a3), 0.0)
    return e * (np.asarray(texture, np.float64)[None] * np.maximum(nl, 0.0) + spec)
