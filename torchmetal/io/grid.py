"""Pixel grids of a capture: every s-th pixel as a capture of its own (the choices' and calibrations' grids)."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture


def stride_grid(h: int, w: int, max_pixels: int) -> tuple[slice, slice, float, float]:
    """(rows, cols, width scale, height scale): every s-th pixel of an H × W grid (s odd, the smallest
    with ≤ ``max_pixels`` pixels), and the factors of the surface size that keep each kept pixel's centre
    where it was (:func:`strided_capture`)."""
    s = 1
    while -(-h // s) * -(-w // s) > max_pixels:
        s += 2

    def axis(n: int) -> tuple[slice, int]:
        # m kept rows at o, o+s, …: centres match when o = (s−1)/2 + (n − m·s)/2, an integer for m ≡ n (mod 2)
        m = n // s
        if (n - m * s) % 2:
            m -= 1
        o = (s - 1) // 2 + (n - m * s) // 2
        return slice(o, o + m * s, s), m

    rows, m_h = axis(h)
    cols, m_w = axis(w)
    return rows, cols, m_w * s / w, m_h * s / h


def strided_capture(capture: Capture, max_pixels: int) -> Capture:
    """Every s-th pixel (s odd, the smallest with ≤ ``max_pixels`` pixels) as a capture of its own, its
    surface size chosen so that each kept pixel's centre is where it was: the same lights, cameras and
    geometry per pixel, at a fraction of the cost. Returns ``capture`` itself when it is small enough."""
    h, w = int(capture.images.shape[-2]), int(capture.images.shape[-1])
    if h * w <= max_pixels:
        return capture
    rows, cols, fw, fh = stride_grid(h, w, max_pixels)
    size = (capture.size[0] * fw, capture.size[1] * fh)
    pick = lambda t: t[..., rows, cols]  # noqa: E731
    return replace(capture, images=pick(capture.images), normals=pick(capture.normals).contiguous(),
                   mask=pick(capture.mask), saturated=pick(capture.saturated), size=size)
