"""Per-pixel sums of the variable-projection problem, and their reduction per element.

The specular refinement (:mod:`torchmetal.fit.refine`) eliminates the texture and s in closed
form; what it needs from the observations are the six projected sums B, C, Bc, Cc, Yc, Sbb
(see that module's docstring). :func:`chunk_stats` computes them for one chunk of pixels and
:func:`reduce_stats` adds them into per-element float64 sums. Both the refinement and the
observation builder (:mod:`torchmetal.fit.problem`, which can accumulate the first pass while it
builds) use them; this module depends on neither.
"""

from __future__ import annotations

import torch
from torch import Tensor


def chunk_stats(
    y: Tensor, a: Tensor, b: Tensor, t: Tensor, w: Tensor, isaa: Tensor, wa: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Per-pixel projected sums of one chunk.

    Args:
        y (n, 3, c) data; a = i·g (n, 3, c) texture basis; b = i·u·exp(t) (n, 3, c) lobe;
        t = α·L (n, 3, c), so ∂b/∂β = t·b; w (n, 3, c) float weights (0/1 validity or IRLS);
        isaa (3, c) = 1/Σ w·a² (0 where none); wa (n, 3, c) = w·a when the caller has it.

    Returns:
        e_b (3, c) and the stats (6, 3, c): B, C, Bc, Cc, Yc, Sbb (see :mod:`torchmetal.fit.refine`).
    """
    wa = w * a if wa is None else wa
    wab = wa * b
    sab = wab.sum(0)
    eb = sab * isaa
    ec = (wab * t).sum(0) * isaa
    bp = torch.addcmul(b, a, eb, value=-1.0)  # b − a·e_b
    cp = torch.addcmul(b * t, a, ec, value=-1.0)  # ∂b/∂β − a·e_c
    wbp = w * bp
    wcp = w * cp
    C = (wbp * bp).sum(0)
    sbb = C + eb * sab  # Σ w·b² = Σ w·b⊥² + e_b²·Σ w·a² (b⊥ ⊥ a), and e_b·Σ w·a² = Σ w·a·b
    stats = torch.stack([(wbp * y).sum(0), C, (wbp * cp).sum(0), (wcp * cp).sum(0), (wcp * y).sum(0), sbb])
    return eb, stats


def reduce_stats(st: Tensor, labels: Tensor | None, k: int, out: Tensor) -> None:
    """Add per-pixel stats (6, 3, c) into per-element sums ``out`` (6, 3, K) float64."""
    st = st.double()
    if labels is None or k == 1:
        out[:, :, 0] += st.sum(-1)
    else:
        out.index_add_(2, labels, st)
