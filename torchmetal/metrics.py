"""Image metrics, in one place: PSNR / MSE, the sRGB encoding they can compare in, MD, sparkle count.

Every number torchmetal reports about how close two images are comes from here, so that the
demo, the report figure, the benchmark, the leave-one-out evaluation and the tests agree.

Convention (the project's): **PSNR on linear values clipped to [0, 1], peak 1**, computed in
float64. Radiance has no fixed white, but a fixed peak makes numbers comparable between images,
shots and methods (a ``ref.max()`` peak rewards an image for having one bright pixel).

===============================  ==============================================================
function                         what it measures
===============================  ==============================================================
:func:`psnr`                     10·log10(peak² / MSE) in dB, optionally masked, linear or sRGB
:func:`mse`                      mean squared difference, optionally masked and clipped
:func:`srgb_encode`              linear → sRGB (IEC 61966-2-1 OETF), torch or numpy
:func:`md`                       the paper's Metallic Difference (:mod:`torchmetal.flakes.model.md`)
:func:`sparkle_count`            connected bright blobs in a residual above k robust σ
:func:`chroma_artifact_share`    share of 8×8 blocks whose CIELAB chroma differs by > 15
===============================  ==============================================================

Inputs are torch tensors or numpy arrays in any layout (``(…, 3, H, W)`` or ``(…, H, W, 3)``);
PSNR and MSE are element-wise, so only the two shapes and the mask's broadcast matter. Importing
this module is cheap: torch, numpy and the flake render model's MD (:mod:`torchmetal.flakes.model.md`, torch
only); OpenCV and kornia are imported when first used.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchmetal.errors import InputError
from torchmetal.flakes.model.md import metallic_difference
from torchmetal.io.images import linear_to_srgb

__all__ = ["psnr", "mse", "srgb_encode", "md", "sparkle_count", "chroma_artifact_share"]

_MAD_TO_SIGMA = 1.4826  # σ of a normal distribution = 1.4826 · its median absolute deviation


# ---------------------------------------------------------------------------------------------
# input handling


def _as_f64(x: Any, name: str, device: torch.device | None = None) -> Tensor:
    """A detached float64 tensor of ``x`` (tensor, numpy array or nested sequence)."""
    if isinstance(x, Tensor):
        t = x.detach()
    else:
        try:
            t = torch.from_numpy(np.ascontiguousarray(x, dtype=np.float64))
        except (TypeError, ValueError) as e:
            raise InputError(f"{name}: expected a tensor or a numeric array, found {type(x).__name__} ({e})") from None
    if t.is_complex():
        raise InputError(f"{name}: expected real values, found dtype {t.dtype}")
    if device is not None and t.device != device:
        t = t.to(device)
    if t.device.type == "mps":  # no float64 there
        t = t.cpu()
    return t.to(torch.float64)


def _mask_for(mask: Any, shape: torch.Size, device: torch.device) -> Tensor:
    """Boolean mask broadcast to ``shape`` (an (H, W) mask also fits an (…, H, W, 3) image)."""
    m = mask.detach() if isinstance(mask, Tensor) else torch.from_numpy(np.ascontiguousarray(mask))
    m = m.to(device)
    if m.dtype != torch.bool:
        if m.is_complex() or not bool(((m == 0) | (m == 1)).all()):
            raise InputError("mask: expected a bool or 0/1 array, found other values")
        m = m != 0
    try:
        return torch.broadcast_to(m, shape)
    except RuntimeError:
        pass
    if len(shape) >= 3 and shape[-1] == 3 and tuple(m.shape[-2:]) == tuple(shape[-3:-1]):
        try:  # (H, W) or (N, H, W) mask for a channels-last image
            return m.unsqueeze(-1).expand(shape)
        except RuntimeError:
            pass
    raise InputError(f"mask: expected a shape broadcastable to {tuple(shape)}, found {tuple(m.shape)}")


def _prepare(pred: Any, ref: Any, mask: Any, clip: bool, fn: str) -> tuple[Tensor, Tensor, Tensor | None]:
    """float64 pred, ref (checked: equal shapes, finite where counted, clipped if asked) and mask."""
    p = _as_f64(pred, "pred")
    r = _as_f64(ref, "ref", p.device)
    if p.shape != r.shape:
        raise InputError(f"{fn}: expected ref of pred's shape {tuple(p.shape)}, found {tuple(r.shape)}")
    m = None if mask is None else _mask_for(mask, p.shape, p.device)
    n = p.numel() if m is None else int(m.sum())
    if n == 0:
        what = "the mask selects none" if m is not None else "the inputs are empty"
        raise InputError(f"{fn}: expected at least one element to compare, {what}")
    finite = torch.isfinite(p) & torch.isfinite(r)
    bad = ~finite if m is None else ~finite & m
    if bool(bad.any()):
        raise InputError(f"{fn}: expected finite values, found {int(bad.sum())} non-finite of {n} compared")
    if clip:
        p, r = p.clamp(0.0, 1.0), r.clamp(0.0, 1.0)
    return p, r, m


def _mse(p: Tensor, r: Tensor, m: Tensor | None) -> float:
    d2 = (p - r).square()
    if m is None:
        return float(d2.mean())
    return float(torch.where(m, d2, torch.zeros((), dtype=d2.dtype, device=d2.device)).sum() / int(m.sum()))


# ---------------------------------------------------------------------------------------------
# metrics


def srgb_encode(x: Tensor | np.ndarray) -> Tensor | np.ndarray:
    """Linear → sRGB, the IEC 61966-2-1 OETF (12.92·x up to 0.0031308, then 1.055·x^(1/2.4) − 0.055).

    The curve itself is :func:`torchmetal.io.images.linear_to_srgb` (one implementation in the
    package); this wrapper also takes numpy arrays. No clipping: values above 1 follow the power
    branch, negative values the linear one.

    Args:
        x: tensor or numpy array of any shape (floating point).

    Returns:
        the same type, shape and dtype as ``x``.
    """
    if isinstance(x, Tensor):
        return linear_to_srgb(x)
    a = np.asarray(x)
    dtype = a.dtype if np.issubdtype(a.dtype, np.floating) else np.float64
    out = linear_to_srgb(torch.from_numpy(np.ascontiguousarray(a, dtype=np.float64))).numpy()
    return out.astype(dtype, copy=False)


def mse(pred: Tensor | np.ndarray, ref: Tensor | np.ndarray, *, mask: Any = None, clip: bool = True) -> float:
    """Mean squared difference of ``pred`` and ``ref`` over the mask, in float64.

    Args:
        pred, ref: tensors or numpy arrays of the same shape, any layout (e.g. ``(…, 3, H, W)``
            or ``(…, H, W, 3)``), linear values.
        mask: optional bool (or 0/1) array broadcastable to ``pred`` — ``(H, W)``,
            ``(1, 1, H, W)``, ``(N, 1, H, W)``, ``(N, 3, H, W)``, …; an ``(H, W)`` mask also fits
            an ``(…, H, W, 3)`` image. Only mask-true elements count (a mask broadcast over the
            channels counts every channel of its pixels).
        clip: clip both to [0, 1] first (the project's convention).

    Returns:
        the MSE (a float ≥ 0).

    Raises:
        InputError: shapes differ, the mask selects nothing, or a compared value is not finite.
    """
    p, r, m = _prepare(pred, ref, mask, clip, "mse")
    return _mse(p, r, m)


def psnr(
    pred: Tensor | np.ndarray,
    ref: Tensor | np.ndarray,
    *,
    mask: Any = None,
    peak: float = 1.0,
    space: str = "linear",
    clip: bool = True,
) -> float:
    """Peak signal-to-noise ratio in dB, 10·log10(peak² / MSE), computed in float64.

    The project's convention is the default: linear values clipped to [0, 1], peak 1.

    Args:
        pred, ref: tensors or numpy arrays of the same shape, any layout (e.g. ``(…, 3, H, W)``
            or ``(…, H, W, 3)``); element-wise, so the layout does not matter.
        mask: optional bool (or 0/1) array broadcastable to ``pred`` (see :func:`mse`); only
            mask-true elements count. Values outside the mask may be anything, NaN included.
        peak: the signal peak (> 0).
        space: "linear" — the values as given; "srgb" — both clipped to [0, 1] and encoded with
            :func:`srgb_encode` before comparing (a perceptual-ish PSNR of the displayed image).
        clip: clip both to [0, 1] before comparing ("srgb" always clips).

    Returns:
        PSNR in dB; ``inf`` when the compared values are identical.

    Raises:
        InputError: shapes differ, the mask selects nothing, a compared value is not finite, or
            ``peak`` / ``space`` are invalid.
    """
    if isinstance(peak, bool) or not isinstance(peak, (int, float)) or not (math.isfinite(peak) and peak > 0):
        raise InputError(f"psnr: expected a finite peak > 0, found {peak!r}")
    if space not in ("linear", "srgb"):
        raise InputError(f"psnr: expected space 'linear' or 'srgb', found {space!r}")
    p, r, m = _prepare(pred, ref, mask, clip or space == "srgb", "psnr")
    if space == "srgb":
        p, r = srgb_encode(p), srgb_encode(r)
    e = _mse(p, r, m)
    if e == 0.0:
        return math.inf
    return 10.0 * math.log10(float(peak) ** 2 / e)


def md(
    img_a: Tensor,
    img_b: Tensor,
    window: int = 16,
    *,
    k: float = 5.0,
    regions: int = 1,
    reduction: str = "mean",
) -> float | Tensor:
    """The paper's Metallic Difference, a sparkle-aware distance in [0, 100] (lower = closer).

    A thin wrapper of :func:`torchmetal.flakes.model.md.metallic_difference` (see that module for the
    definition): the flake render model's layer lies below this module, so it imports MD directly.

    Args:
        img_a, img_b: (H, W), (C, H, W) or (B, C, H, W) linear torch images of the same shape,
            at least ``window`` pixels per side.
        window: block size in pixels.
        k: sparkle threshold in units of the larger robust noise σ of the two high-passes.
        regions: compare regions×regions areas separately (1 = the whole image).
        reduction: "mean" → a float over the batch; "none" → a (B,) tensor.

    Returns:
        MD in [0, 100].
    """
    return metallic_difference(img_a, img_b, window, k=k, regions=regions, reduction=reduction)


def sparkle_count(residual: Tensor | np.ndarray, *, k: float = 5.0, mask: Any = None) -> int:
    """Number of connected bright blobs (sparkles) in a residual image.

    The residual is a photo minus a smooth (e.g. Phong) render. Its noise σ is the robust
    1.4826·MAD of all its channels over the mask; a pixel is bright when the maximum over its
    channels exceeds the residual's median by more than k·σ. Bright mask pixels are grouped
    8-connected (``cv2.connectedComponents``) and the groups counted.

    Args:
        residual: (3, H, W) or (H, W, 3) tensor or numpy array (also (1, H, W) or (H, W));
            a leading dimension of 3 (or 1) is read as channels-first.
        k: threshold in robust σ (> 0).
        mask: optional bool (or 0/1) ``(H, W)`` array (``(1, H, W)`` / ``(H, W, 1)`` too): only
            these pixels are bright candidates and enter the noise estimate.

    Returns:
        the number of blobs (0 when nothing exceeds the threshold).

    Raises:
        InputError: wrong shape, ``k`` invalid, the mask selects nothing, or a masked value is
            not finite.
    """
    import cv2

    if isinstance(k, bool) or not isinstance(k, (int, float)) or not (math.isfinite(k) and k > 0):
        raise InputError(f"sparkle_count: expected a finite k > 0, found {k!r}")
    x = _as_f64(residual, "residual").cpu()
    shape = tuple(x.shape)
    if x.dim() == 2:
        x = x[None]
    elif x.dim() == 3 and x.shape[0] not in (1, 3) and x.shape[-1] in (1, 3):
        x = x.permute(2, 0, 1)
    if x.dim() != 3 or x.shape[0] not in (1, 3):
        raise InputError(f"sparkle_count: expected a residual (3, H, W) or (H, W, 3), found {shape}")
    h, w = x.shape[-2:]
    if mask is None:
        m = torch.ones(h, w, dtype=torch.bool)
    else:
        mm = mask.detach().cpu() if isinstance(mask, Tensor) else torch.from_numpy(np.ascontiguousarray(mask))
        if mm.dim() == 3 and mm.shape[-1] == 1 and mm.shape[0] != 1:
            mm = mm[..., 0]
        if tuple(mm.shape[-2:]) != (h, w) or mm.numel() != h * w:
            raise InputError(f"sparkle_count: expected a mask of shape ({h}, {w}), found {tuple(mm.shape)}")
        m = _mask_for(mm.reshape(h, w), torch.Size((h, w)), torch.device("cpu"))
    if not bool(m.any()):
        raise InputError("sparkle_count: expected at least one pixel, the mask selects none")
    vals = x[:, m]  # (C, n)
    if not bool(torch.isfinite(vals).all()):
        n_bad = int((~torch.isfinite(vals)).sum())
        raise InputError(f"sparkle_count: expected finite values, found {n_bad} non-finite in the mask")
    med = vals.median()
    sigma = _MAD_TO_SIGMA * float((vals - med).abs().median())
    bright = ((x.amax(0) - med) > k * sigma) & m
    n, _ = cv2.connectedComponents(bright.numpy().astype(np.uint8), connectivity=8)
    return int(n) - 1


def chroma_artifact_share(pred: Tensor | np.ndarray, ref: Tensor | np.ndarray, *, block: int = 8,
                          threshold: float = 15.0, mask: Any = None) -> float:
    """Fraction of ``block``×``block``-pixel blocks where ``pred`` and ``ref`` differ in colour: CIELAB
    chroma distance √(Δa*² + Δb*²) > ``threshold`` between the blocks' mean colours.

    Each block's mean linear colour is sRGB-encoded (clipped to [0, 1]) and converted with
    ``kornia.color.rgb_to_lab`` (D65); lightness is left out, so a render that is only too bright or
    too dark scores 0 — the metric counts colour casts (a gold highlight where the photo is grey, a
    missing teal). Blocks that do not fit whole at the right and bottom edges are left out.

    Args:
        pred, ref: linear RGB images, (3, H, W) or (B, 3, H, W) (tensor or numpy).
        block: block size in pixels.
        threshold: chroma distance above which a block counts (≈ clearly visible; ΔE 2.3 is a JND).
        mask: optional (H, W) or broadcastable bool; a block counts only where it is wholly inside.

    Returns:
        the share in [0, 1] (NaN when no block qualifies).
    """
    from kornia.color import rgb_to_lab  # on use: this module's import stays torch + numpy

    p, r, m = _prepare(pred, ref, mask, clip=False, fn="chroma_artifact_share")
    if p.dim() == 3:
        p, r = p.unsqueeze(0), r.unsqueeze(0)
        m = None if m is None else m.unsqueeze(0)
    if p.dim() != 4 or p.shape[1] != 3:
        raise InputError(f"chroma_artifact_share: expected (3, H, W) or (B, 3, H, W) images, found {tuple(p.shape)}")
    h, w = (p.shape[-2] // block) * block, (p.shape[-1] // block) * block
    if h == 0 or w == 0:
        return math.nan
    pool = lambda x: torch.nn.functional.avg_pool2d(x[..., :h, :w], block)  # noqa: E731
    lab_p = rgb_to_lab(srgb_encode(pool(p).clamp(0.0, 1.0)).float())
    lab_r = rgb_to_lab(srgb_encode(pool(r).clamp(0.0, 1.0)).float())
    dist = (lab_p[:, 1:] - lab_r[:, 1:]).double().square().sum(1).sqrt()  # (B, h/b, w/b)
    keep = torch.ones_like(dist, dtype=torch.bool)
    if m is not None:
        mm = m.expand(p.shape[0], -1, -1, -1).all(1, keepdim=True).double()
        keep = pool(mm)[:, 0] > 0.999
    n = int(keep.sum())
    return float((dist > threshold)[keep].sum()) / n if n else math.nan
