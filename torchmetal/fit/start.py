"""Where a refit of a chosen model starts: the values and choices of the fit that chose it.

The choices before the Phong fit (:mod:`torchmetal.select.choices`) fit their candidates with the model a reference
fit chose: the same lobe, specular structure and weights on other shots, another pixel grid, other normals or
lights. Those refits need not find again what the reference fit found: where the lobe peaks (the paper's scheme and
the α grid), how noisy the camera is (the noise model, a property of the photos), whether a highlight is there (its
held-out test) and its specular colour. A :class:`Start` carries them into :func:`~torchmetal.fit.fit_phong`; the
refit still solves every value from its own data, and splits its clusters from its own shots: on random scenes a
refit that kept the reference's feature set moved five choices by 1.5-17 dB, both ways (docs/measurements.md).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

if TYPE_CHECKING:
    from torchmetal.fit.result import FitResult


@dataclass(frozen=True)
class Start:
    """A fitted model's values and choices, for its refits (module docstring).

    Attributes:
        lobe, specular: the lobe and specular structure the values belong to (a refit of another lobe or
            structure, such as the global fits of a clustered model's normal estimate, starts from scratch).
        s: (1, 3) float64: the global lobe's strength (a clustered fit's area mean): with ``alpha[:1]``, the model
            value the refit's noise weights are computed at.
        alpha: (M, 3) float64: the global lobe's α (a clustered fit's area mean), then each cluster's: the LM
            starts, per channel, from the one that fits the refit's subsample best (a clustered fit's area mean
            can lie far from any global optimum: α 6 / 675 / 5 per channel on one random scene).
        variance: (2, 3) float64 noise model (a, b) of :class:`~torchmetal.fit.problem.Weighting`, or None
            (uniform weights).
        white: one s for the three channels (:mod:`torchmetal.fit.colour`).
        per_channel: a GGX fit that kept an α per channel (its likelihood-ratio test,
            :func:`~torchmetal.fit.refine.share_alpha`, told the channels apart): its refits keep them untested — the
            test costs four full-size passes, and the same photos less a few glints tell the channels apart as well
            (docs/measurements.md, eighth session).
    """

    lobe: str
    specular: str
    s: Tensor
    alpha: Tensor
    variance: Tensor | None = None
    white: bool = False
    per_channel: bool = False

    @classmethod
    def of(cls, fit: FitResult) -> Start | None:
        """The start ``fit`` gives its refits; None where it kept no specular lobe (nothing to start from)."""
        if fit.specular == "none":
            return None
        chosen = {d["name"]: d["chosen"] for d in fit.decisions}
        variance = None if fit.noise is None else torch.tensor([fit.noise["a"], fit.noise["b"]], dtype=torch.float64)
        alpha = fit.alpha.detach().double().reshape(1, 3)
        if fit.cluster_alpha is not None:
            alpha = torch.cat([alpha, fit.cluster_alpha.detach().double().reshape(-1, 3)])
        # the sharing test ran (GGX without maps: fit.api) and kept three α (a shared α has equal channels)
        per_channel = fit.lobe == "ggx" and fit.specular != "maps" and bool((alpha != alpha[:, :1]).any())
        return cls(lobe=fit.lobe, specular=fit.specular, s=fit.s.detach().double().reshape(1, 3), alpha=alpha,
                   variance=variance, white=chosen.get("specular colour") == "white", per_channel=per_channel)

    def to(self, device: torch.device) -> Start:
        """This start with its tensors on ``device``."""
        move = lambda t: None if t is None else t.to(device)  # noqa: E731
        return replace(self, s=move(self.s), alpha=move(self.alpha), variance=move(self.variance))


def refit_options(fit: FitResult, *, maps: bool = True) -> dict:
    """:func:`~torchmetal.fit.fit_phong` options that refit ``fit``'s model without choosing it again: its lobe,
    specular structure (a clustered fit's cluster count, and relabelling only where it relabelled), weights, and
    its :class:`Start`. ``maps`` False: a gloss-maps model as the structure its maps started from (its clusters, or
    one lobe), for refits on too few shots to determine per-pixel gloss (:mod:`torchmetal.select.choices`)."""
    sel = fit.selection or {}
    specular = fit.specular
    start = Start.of(fit)
    if specular == "maps" and not maps:
        specular = "clustered" if int(sel.get("k") or 1) > 1 else "global"
        # the maps' own α (their mean, and each cluster's) start the structure they grew from: a start of another
        # structure is dropped (fit_phong), and every refit would then search for the lobe again (paper scheme, α grid)
        start = None if start is None else replace(start, specular=specular)
    model = {"lobe": fit.lobe, "specular": specular, "weights": "noise" if fit.noise is not None else "uniform",
             "start": start}
    if specular == "clustered" and sel.get("k"):
        model |= {"clusters": (int(sel["k"]),), "relabel": bool(sel.get("relabel"))}
    return model
