"""The per-observation geometry of a pixel grid — (g, u, L) and GGX's ``geo`` — in bulk or per chunk.

The terms are those of :mod:`torchmetal.fit.problem` (shot k, pixel p):

    g_kp = max(n·l, 0)/dist²,   u_kp = [n·l > 0]/dist²,   L_kp = log max(r·v, 0) = log1p(−q)

built separably on the plane's pixel grid (:func:`torchmetal.geometry.grid_shading_terms`).
A fit's subsamples store them ((N, 1, P) each, small at a stride). At full resolution they would
take as much memory as the capture itself (three float32 values per pixel and shot, against the
capture's three colours), so the full-resolution pass streams them instead: :class:`GridSource`
recomputes one chunk's terms and validity each time the chunk is visited, with the same formulas
on the same rows — the same values bit for bit, whatever the chunking.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.fit.lobes import LOG_OFF, observation_lobe_terms
from torchmetal.geometry import grid_shading_terms, is_flat, pixel_axes
from torchmetal.lobes import grid_half_terms
from torchmetal.phong import lobe_log

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture


def observation_geometry(n_dot_l: Tensor, spec_q: Tensor, dist2: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(g, u, L) of the module docstring from n·l, q = 1 − r·v and the squared light distance.

    g = max(n·l, 0)/dist², u = [n·l > 0]/dist², L = log1p(−q) (``LOG_OFF`` where r·v ≤ 0); any
    shapes that broadcast, e.g. (n, R, C).
    """
    u = torch.where(n_dot_l > 0, 1.0 / dist2, 0.0)
    inside = spec_q < 1.0
    L = torch.where(inside, lobe_log(spec_q, inside), LOG_OFF)
    return n_dot_l * u, u, L


def block_terms(lights: Tensor, cams: Tensor, xs: Tensor, ys: Tensor, normals: Tensor | None,
                lobe: str) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """(g, u, L) (n, R, C) each and GGX's geo (3, n, R, C) (else None) of the grid ``ys`` × ``xs``.

    lights, cams (n, 4); normals (3, R, C) or None for the flat normal. For ``lobe`` "blinn" L is
    log n·h, for "ggx" L and geo are :func:`~torchmetal.fit.lobes.observation_lobe_terms`'s.
    """
    nl, q, d2 = grid_shading_terms(lights, cams, xs, ys, normals)
    if lobe == "phong":
        g, u, L = observation_geometry(nl, q, d2)
        return g, u, L, None
    hq, nv, vh = grid_half_terms(lights, cams, xs, ys, normals)
    g, u, log_cos = observation_geometry(nl, hq, d2)
    L, geo = observation_lobe_terms(lobe, nl, q, hq, nv, vh, log_cos)
    return g, u, L, geo


def grid_axes(capture: Capture, rows: slice, cols: slice, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor | None]:
    """x of the columns (C,), y of the rows (R,) and the normals (3, R, C) of the grid, None when
    they are all the flat (0, 0, 1) (the cheaper path of the shading terms)."""
    big_h, big_w = int(capture.images.shape[-2]), int(capture.images.shape[-1])
    xs, ys = pixel_axes(big_h, big_w, capture.size, rows=rows, cols=cols, dtype=dtype, device=capture.images.device)
    normals = capture.normals[:, rows, cols]
    return xs, ys, None if is_flat(normals) else normals


def grid_geometry(
    capture: Capture, rows: slice, cols: slice, lights: Tensor, cams: Tensor, dtype: torch.dtype, block_rows: int,
    *, out: tuple[Tensor, Tensor, Tensor], lobe: str = "phong", geo_out: Tensor | None = None,
) -> None:
    """Fill ``out`` = (g, u, L), each (n, 1, R·C), for the pixel grid ``rows`` × ``cols``.

    lights, cams (n, 4) in ``dtype``. Works in blocks of ``block_rows`` grid rows (memory only:
    every term is per pixel, so the values do not depend on it); ``geo_out`` (n, 3, R·C) for GGX.
    """
    xs, ys, normals = grid_axes(capture, rows, cols, dtype)
    n, h, w = int(lights.shape[0]), int(ys.shape[0]), int(xs.shape[0])
    for r0 in range(0, h, block_rows):
        r1 = min(h, r0 + block_rows)
        nrm = None if normals is None else normals[:, r0:r1].to(dtype)
        g, u, L, geo = block_terms(lights, cams, xs, ys[r0:r1], nrm, lobe)
        if geo is not None:
            geo_out[:, :, r0 * w : r1 * w] = geo.reshape(3, n, (r1 - r0) * w).transpose(0, 1)
        for dst, src in zip(out, (g, u, L)):
            dst[:, 0, r0 * w : r1 * w] = src.reshape(n, (r1 - r0) * w)


def base_validity(g: Tensor, mask: Tensor | None, inten_pos: Tensor, sat: Tensor | None) -> Tensor:
    """(n, 3, c) bool: lit (g > 0), inside the mask, a positive intensity, not saturated.

    g (n, 1, c); mask (1, 1, c) bool or None; inten_pos (n, 3, 1) bool; sat (n, 3, c) bool or None.
    """
    lit = g > 0
    if mask is not None:
        lit = lit & mask
    base = lit & inten_pos
    return base if sat is None else base & ~sat


BLOCK_ELEMENTS = 1 << 18  # pixel-shots per block a GridSource computes at once (1 MiB per float32 term)


@dataclass
class GridSource:
    """Recomputes the terms and validity of pixels [p0, p1) of a w-wide grid (flattened row-major).

    Terms are computed for every shot on blocks of whole rows (≥ :data:`BLOCK_ELEMENTS` pixel-shots,
    far fewer operations than chunk by chunk) and the last block is kept: the chunks inside it, and
    a chunk's GGX geometry after its terms, are slices of it. ``mask`` (1, 1, P) and ``sat``
    (n, 3, P) are views of the capture's (no copies).
    """

    lights: Tensor  # (n, 4)
    cams: Tensor  # (n, 4)
    xs: Tensor  # (w,)
    ys: Tensor  # (h,)
    normals: Tensor | None  # (3, h, w) or None (flat)
    lobe: str
    inten_pos: Tensor  # (n, 3, 1) bool
    mask: Tensor | None  # (1, 1, P) bool
    sat: Tensor | None  # (n, 3, P) bool
    dtype: torch.dtype
    _block: tuple | None = field(default=None, repr=False)  # (q0, q1, (g, u, L, geo, base))

    def _compute(self, p0: int, p1: int) -> tuple:
        w, n = int(self.xs.shape[0]), int(self.lights.shape[0])
        r0 = p0 // w
        r1 = min(int(self.ys.shape[0]), max(-(-p1 // w), r0 + max(1, BLOCK_ELEMENTS // max(1, n * w))))
        q0, q1 = r0 * w, r1 * w
        nrm = None if self.normals is None else self.normals[:, r0:r1]
        g, u, L, geo = block_terms(self.lights, self.cams, self.xs, self.ys[r0:r1], nrm, self.lobe)
        g, u, L = (t.reshape(n, 1, q1 - q0) for t in (g, u, L))
        if geo is not None:
            geo = geo.reshape(3, n, q1 - q0).transpose(0, 1)
        mask = None if self.mask is None else self.mask[:, :, q0:q1]
        sat = None if self.sat is None else self.sat[:, :, q0:q1]
        self._block = (q0, q1, (g, u, L, geo, base_validity(g, mask, self.inten_pos, sat)))
        return self._block

    def terms(self, p0: int, p1: int, shots: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor]:
        """(g, u, L) (n, 1, c), geo (n, 3, c) or None, validity (n, 3, c) bool, for ``shots`` (default all)."""
        blk = self._block
        if blk is None or not (blk[0] <= p0 and p1 <= blk[1]):
            blk = self._compute(p0, p1)
        q0, _, full = blk
        out = tuple(None if t is None else t[:, :, p0 - q0 : p1 - q0] for t in full)
        return out if shots is None else tuple(None if t is None else t.index_select(0, shots) for t in out)
