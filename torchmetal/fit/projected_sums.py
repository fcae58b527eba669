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
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-pixel projected sums of one chunk.

    Args:
        y (n, 3, c) data; a = i·g (n, 3, c) texture basis; b = i·u·exp(t) (n, 3, c) lobe;
        t = α·L (n, 3, c), so ∂b/∂β = t·b; w (n, 3, c) float weights (0/1 validity or IRLS);
        isaa (3, c) = 1/Σ w·a² (0 where none); wa (n, 3, c) = w·a when the caller has it.

    Returns:
        e_b (3, c), e_c (3, c) and the stats (6, 3, c): B, C, Bc, Cc, Yc, Sbb (see
        :mod:`torchmetal.fit.refine`).
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
    return eb, ec, stats


def add_skipped_shots(stats: Tensor, eb: Tensor, ec: Tensor, y: Tensor, a: Tensor, wa: Tensor, saa: Tensor,
                      d0: Tensor) -> Tensor:
    """Stats (6, 3, c) of a chunk computed on some shots only, completed for the shots left out
    because their lobe is negligible (b = 0).

    A left-out shot still couples through the texture: its b⊥ = −a·e_b and c⊥ = −a·e_c, so it
    adds e_b²·Σ'w·a² to C, −e_b·Σ'w·a·y to B, e_b·e_c·Σ'w·a² to Bc, e_c²·Σ'w·a² to Cc and
    −e_c·Σ'w·a·y to Yc, Σ' over the left-out shots. Σ w·b² itself is unchanged, but
    :func:`chunk_stats` forms it as C + e_b·Σ w·a·b, so Sbb takes C's correction too.

    Args:
        stats, eb, ec: :func:`chunk_stats` of the shots kept; y, a, wa (n, 3, c) those shots'
            data, texture basis and weighted basis w·a; saa = Σ w·a² and d0 = Σ w·a·y / Σ w·a² (3, c) over
            all shots (:class:`~torchmetal.fit.problem.Observations`), so Σ' = all − kept.
    """
    saa_rest = (saa - (wa * a).sum(0)).clamp_min(0.0)
    say_rest = d0 * saa - (wa * y).sum(0)
    B, C, Bc, Cc, Yc, sbb = stats.unbind(0)
    return torch.stack([B - eb * say_rest, C + eb * eb * saa_rest, Bc + eb * ec * saa_rest, Cc + ec * ec * saa_rest,
                        Yc - ec * say_rest, sbb + eb * eb * saa_rest])


def reduce_stats(st: Tensor, labels: Tensor | None, k: int, out: Tensor) -> None:
    """Add per-pixel stats (6, 3, c) into per-element sums ``out`` (6, 3, K) float64."""
    st = st.double()
    if labels is None or k == 1:
        out[:, :, 0] += st.sum(-1)
    else:
        out.index_add_(2, labels, st)
