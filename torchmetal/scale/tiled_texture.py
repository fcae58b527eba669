"""The texture step of the tiled fit: which texels no shot determines, and their inpainting.

The in-memory fit (``fit_phong``'s texture step) calls a texel unobserved when Σw·a² is below
1e-3 × its median over the observed pixels (:func:`~torchmetal.fit.refine.unobserved`), and fills
those from their neighbours (:func:`~torchmetal.fit.refine.fill_unobserved`: a 3×3 box filter
grown ring by ring, at most 64 rings). Tile by tile, with the same values:

- the median is exact: a radix selection on the float32 bit patterns (positive floats sort like
  their bits), 16 high bits from one pass over the tiles, the 16 low bits of the chosen bucket
  from a second pass, and that only when some observed value could fall below the threshold;
- the filling runs on each tile that has unobserved texels plus a margin of 64 pixels: after at
  most 64 rings a texel depends only on texels within 64 pixels, so the tile's values are those
  of the whole image. Texels still unknown after 64 rings take a global median in the in-memory
  fit; the tiled fit refuses that case with a one-line error.
"""

from __future__ import annotations

from typing import Callable, Iterable

import numpy as np
import torch
from torch import Tensor

from torchmetal.errors import FitError
from torchmetal.fit.refine import WEAK_REL, fill_unobserved

FILL_RINGS = 64  # fill_unobserved's default max_iters
_BUCKETS = 1 << 16


def _bits(x: Tensor) -> Tensor:
    """int64 bit patterns of positive float32 values (monotonic in the value)."""
    return x.to(torch.float32).contiguous().view(torch.int32).to(torch.int64)


class SeenStats:
    """Per-channel statistics of Σw·a² over observed pixels (> 0), accumulated tile by tile."""

    def __init__(self) -> None:
        self.hist = torch.zeros(3, _BUCKETS, dtype=torch.int64)
        self.lo = torch.full((3,), torch.inf, dtype=torch.float32)
        self.hi = torch.zeros(3, dtype=torch.float32)

    def add(self, saa: Tensor) -> None:
        """saa (3, P) of one tile."""
        for c in range(3):
            v = saa[c][saa[c] > 0]
            if v.numel():
                self.hist[c] += torch.bincount(_bits(v) >> 16, minlength=_BUCKETS)
                self.lo[c] = torch.minimum(self.lo[c], v.min().float())
                self.hi[c] = torch.maximum(self.hi[c], v.max().float())

    def merge(self, other: "SeenStats") -> None:
        self.hist += other.hist
        self.lo = torch.minimum(self.lo, other.lo)
        self.hi = torch.maximum(self.hi, other.hi)

    def needs_median(self) -> bool:
        """False when no observed value can fall below 1e-3 × the median (it is ≤ the largest)."""
        return bool((self.lo < WEAK_REL * self.hi).any())

    def buckets(self) -> tuple[Tensor, Tensor, Tensor]:
        """(rank of the median, its bucket of high bits, the count below that bucket), each (3,)."""
        count = self.hist.sum(1)
        rank = (count - 1).clamp_min(0) // 2
        cum = self.hist.cumsum(1)
        bucket = torch.stack([torch.searchsorted(cum[c], rank[c], right=True) for c in range(3)])
        before = torch.stack([cum[c, bucket[c] - 1] if bucket[c] > 0 else torch.zeros((), dtype=torch.int64)
                              for c in range(3)])
        return rank, bucket, before

    @staticmethod
    def low_bits(saa: Tensor, bucket: Tensor) -> Tensor:
        """(3, 65536) histogram of the low 16 bits of the observed values in ``bucket`` (3,)."""
        low = torch.zeros(3, _BUCKETS, dtype=torch.int64)
        for c in range(3):
            b = _bits(saa[c][saa[c] > 0])
            b = b[(b >> 16) == bucket[c]]
            if b.numel():
                low[c] += torch.bincount(b & 0xFFFF, minlength=_BUCKETS)
        return low

    def median(self, low_hists: Callable[[Tensor], Iterable[Tensor]]) -> Tensor:
        """(3,) float32: torch's median (the lower one for an even count) of the observed values;
        ``low_hists(bucket)`` yields every tile's :meth:`low_bits` for the chosen buckets."""
        count = self.hist.sum(1)
        rank, bucket, before = self.buckets()
        low = torch.zeros(3, _BUCKETS, dtype=torch.int64)
        for part in low_hists(bucket):
            low += part
        med = torch.zeros(3, dtype=torch.float32)
        for c in range(3):
            if count[c] == 0:
                continue
            j = int(torch.searchsorted(low[c].cumsum(0), rank[c] - before[c], right=True))
            pattern = torch.tensor([(int(bucket[c]) << 16) | j], dtype=torch.int32)
            med[c] = pattern.view(torch.float32)[0]
        return med


def unobserved_tile(saa: Tensor, inside: Tensor, med: Tensor) -> Tensor:
    """(3, P) bool, as :func:`~torchmetal.fit.refine.unobserved` with the whole image's median."""
    return inside.view(1, -1) & (saa < WEAK_REL * med.to(saa.dtype).view(3, 1))


def fill_tiles(raw: np.ndarray, bad: np.ndarray, tiles: list[tuple[slice, slice]], out: np.ndarray) -> None:
    """Inpaint the texels ``bad`` (H, W, 3) of ``raw`` (H, W, 3) as the whole-image
    :func:`~torchmetal.fit.refine.fill_unobserved` would, tile by tile with a 64-pixel margin,
    and write ``raw`` clamped at 0 into ``out`` (H, W, 3)."""
    h, w = raw.shape[:2]
    for rows, cols in tiles:
        b = bad[rows, cols]
        if not b.any():
            out[rows, cols] = np.maximum(raw[rows, cols], 0.0)
            continue
        r0, r1 = max(0, rows.start - FILL_RINGS), min(h, rows.stop + FILL_RINGS)
        c0, c1 = max(0, cols.start - FILL_RINGS), min(w, cols.stop + FILL_RINGS)
        win = torch.from_numpy(np.ascontiguousarray(raw[r0:r1, c0:c1].transpose(2, 0, 1)))
        win_bad = torch.from_numpy(np.ascontiguousarray(bad[r0:r1, c0:c1].transpose(2, 0, 1)))
        filled = _fill_or_refuse(win, win_bad, rows.start - r0, rows.stop - r0, cols.start - c0, cols.stop - c0)
        out[rows, cols] = filled.clamp_min(0.0).permute(1, 2, 0).numpy()


def _fill_or_refuse(win: Tensor, bad: Tensor, i0: int, i1: int, j0: int, j1: int) -> Tensor:
    """The filled interior [i0:i1, j0:j1] of a window; texels beyond 64 rings of any observed one
    (the whole-image fill gives them a global median) are refused."""
    known = ~bad
    grown = known.clone()
    for _ in range(FILL_RINGS):  # reach of the rings, as fill_unobserved's loop grows them
        if bool(grown.all()):
            break
        nxt = torch.nn.functional.max_pool2d(grown.unsqueeze(0).float(), 3, stride=1, padding=1)[0] > 0
        if bool((nxt == grown).all()):
            break
        grown = nxt
    if not bool(grown[:, i0:i1, j0:j1].all()):
        n = int((~grown[:, i0:i1, j0:j1]).any(0).sum())
        raise FitError(f"fit --tile: {n} texel(s) farther than {FILL_RINGS} px from any observed one (the in-memory "
                       "fit gives them the whole texture's median); fit this capture in memory")
    return fill_unobserved(win, bad)[:, i0:i1, j0:j1]
