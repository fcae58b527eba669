"""The outcome of a Phong fit: parameters, what ran, and ways to use them.

``FitResult.render`` renders any light/camera with the capture's normals and size;
``to_material`` makes a :class:`~torchmetal.material.Material` whose report says what ran;
``to_module`` gives a trainable ``nn.Module`` (texture, s, log α — per cluster when clustered)
to keep optimising in a user's own loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from torchmetal.geometry import shading_geometry, surface_points
from torchmetal.lobes import LobeModel, lobe_render, lobe_shading
from torchmetal.material import Material
from torchmetal.phong import PhongModel

if TYPE_CHECKING:
    from torchmetal.select.plan import ShotPlan


class IterationCounts(dict):
    """Iterations per stage (a dict); ``int(counts)`` is the total."""

    def __int__(self) -> int:
        return int(sum(int(v) for v in self.values()))


def skip_stages(skipped: list[str]) -> dict[str, str]:
    """Stage → why, from a report's ``skipped`` list (each entry reads "stage: why"): the stable key of each
    entry, for code that asks *what* was skipped rather than reading the sentence. A stage named twice keeps
    both reasons, joined by "; "."""
    out: dict[str, str] = {}
    for entry in skipped:
        stage, _, why = entry.partition(": ")
        out[stage] = f"{out[stage]}; {why}" if stage in out else why
    return out


class ClusteredPhongModel(nn.Module):
    """Trainable Phong material with per-cluster specular: texture, cluster s and log α (K, 3).

    ``forward(light (B,4), intensity (B,3), camera (B,4)) -> (B,3,H,W)``; s and α reach the
    pixels through the ``labels`` buffer (H, W), so gradients flow to the cluster parameters.
    """

    def __init__(self, texture: Tensor, labels: Tensor, cluster_s: Tensor, cluster_alpha: Tensor,
                 normals: Tensor, size: tuple[float, float], lobe: str = "phong") -> None:
        super().__init__()
        self.lobe = lobe
        h, w = texture.shape[-2:]
        self.size = (float(size[0]), float(size[1]))
        self.texture = nn.Parameter(texture.detach().clone())
        self.cluster_s = nn.Parameter(cluster_s.detach().clone())
        self.cluster_log_alpha = nn.Parameter(torch.log(cluster_alpha.detach().clamp_min(1e-6)))
        self.register_buffer("labels", labels.detach().clone().long())
        self.register_buffer("normals", normals.detach().clone())
        self.register_buffer("points", surface_points(h, w, self.size, dtype=texture.dtype, device=texture.device))

    def maps(self) -> tuple[Tensor, Tensor]:
        """(3, H, W) s and α maps."""
        return self.cluster_s[self.labels].permute(2, 0, 1), torch.exp(self.cluster_log_alpha)[self.labels].permute(2, 0, 1)

    def forward(self, light: Tensor, intensity: Tensor, camera: Tensor) -> Tensor:
        geom = shading_geometry(self.normals, light, intensity, camera, points=self.points)
        s, alpha = self.maps()
        return lobe_shading(self.texture, s, alpha, geom, self.lobe)


@dataclass
class FitResult:
    """Result of :func:`torchmetal.fit.fit_phong`.

    Attributes:
        texture: (3, H, W) diffuse texture d(p).
        s, alpha: (3,) global specular terms (area-weighted cluster means when clustered).
        spec_labels: (H, W) int64 cluster of each pixel, or None (global specular).
        gloss_s, gloss_alpha: (3, H, W) gloss maps (specular="maps"; s, alpha hold their mask means), or None.
        cluster_s, cluster_alpha: (K, 3) or None.
        normals: (3, H, W) the capture's normals; size: (width, height).
        history: one dict per iteration: stage, iter, rmse, active (+ pixels on subsamples).
        stage_times: seconds per stage; iterations: per stage (``int()`` gives the total).
        status: "converged" | "max_iters" | "skipped"; skipped: what was not needed and why, one
            "stage: why" sentence each (``skips``: the same as a dict stage → why).
        rmse: final root-mean-square residual over the valid observations, each weighted as the fit weighs it
            (robust or noise weights, relative to a black observation's; plain least squares: unweighted).
        scheme, specular: what ran ("paper"/"refine"; "global"/"clustered"/"none").
        selection: the held-out comparison behind specular="auto"/"clustered", if any.
        flat: True when every normal is (0, 0, 1).
        lobe: the specular lobe ("phong", docs/design.md §2.2; "blinn"; "ggx"), see :mod:`torchmetal.lobes`.
        lobe_selection: the held-out comparison behind lobe="auto", if any.
        decisions: the :class:`~torchmetal.select.rule.Decision` records (as dicts) of every choice made
            on left-out shots (specular evidence, clusters, relabelling, gloss maps, lobe), in order.
        noise: the noise model the least squares were weighted by, {"a": [3], "b": [3]} (variance
            a + b·ŷ per channel, :func:`~torchmetal.fit.refine.noise_model`), or None (unweighted).
        shot_plan: the shots those choices left out (:class:`~torchmetal.select.plan.ShotPlan`; None
            without a specular fit to plan by); a refit of the same capture is given it.
    """

    texture: Tensor
    s: Tensor
    alpha: Tensor
    normals: Tensor
    size: tuple[float, float]
    spec_labels: Tensor | None = None
    cluster_s: Tensor | None = None
    cluster_alpha: Tensor | None = None
    history: list[dict] = field(default_factory=list)
    stage_times: dict[str, float] = field(default_factory=dict)
    iterations: IterationCounts = field(default_factory=IterationCounts)
    status: str = "converged"
    skipped: list[str] = field(default_factory=list)
    rmse: float = math.nan
    scheme: str = "refine"
    specular: str = "global"
    selection: dict | None = None
    flat: bool = True
    lobe: str = "phong"
    lobe_selection: dict | None = None
    gloss_s: Tensor | None = None
    gloss_alpha: Tensor | None = None
    maps_selection: dict | None = None
    noise: dict | None = None
    decisions: list[dict] = field(default_factory=list)
    shot_plan: ShotPlan | None = None

    @property
    def clustered(self) -> bool:
        return self.spec_labels is not None

    @property
    def skips(self) -> dict[str, str]:
        """``skipped`` keyed by stage (:func:`skip_stages`): ``"specular" in fit.skips``."""
        return skip_stages(self.skipped)

    def specular_maps(self) -> tuple[Tensor, Tensor]:
        """s and α as (3,) globals or, when clustered or with gloss maps, (3, H, W) maps."""
        if self.gloss_s is not None:
            return self.gloss_s, self.gloss_alpha
        if self.spec_labels is None:
            return self.s, self.alpha
        return self.cluster_s[self.spec_labels].permute(2, 0, 1), self.cluster_alpha[self.spec_labels].permute(2, 0, 1)

    def render(self, light: Tensor, intensity: Tensor, camera: Tensor) -> Tensor:
        """Render B shots (B, 3, H, W) with the fitted parameters, the capture's normals and size."""
        dt = self.texture.dtype
        s, alpha = self.specular_maps()
        return lobe_render(self.texture, s, alpha, self.normals, light.to(dt), intensity.to(dt), camera.to(dt), self.size,
                           self.lobe)

    def report(self) -> dict:
        """JSON-able summary: stage times, iterations, history summary, status, skipped, decisions."""
        stages: dict[str, dict] = {}
        for h in self.history:
            st = stages.setdefault(h["stage"], {"iterations": 0, "rmse_first": h["rmse"]})
            st["iterations"] = max(st["iterations"], int(h["iter"]))
            st["rmse_last"] = h["rmse"]
        return {
            "scheme": self.scheme, "specular": self.specular, "status": self.status, "rmse": float(self.rmse),
            "stage_times": {k: float(v) for k, v in self.stage_times.items()},
            "iterations": {k: int(v) for k, v in self.iterations.items()},
            "history": stages, "skipped": list(self.skipped),
            "selection": self.selection,
            "lobe": self.lobe, "lobe_selection": self.lobe_selection,
            "maps_selection": self.maps_selection, "noise": self.noise,
            "decisions": list(self.decisions),
            "shot_plan": None if self.shot_plan is None else self.shot_plan.to_dict(),
        }

    def to_material(self, report_extra: dict | None = None) -> Material:
        """The fit as a :class:`Material` (normals kept only when not flat)."""
        rep = self.report()
        if report_extra:
            rep.update(report_extra)
        return Material(
            texture=self.texture.detach().float(), s=self.s.detach().float(), alpha=self.alpha.detach().float(),
            size=self.size, normals=None if self.flat else self.normals.detach().float(),
            spec_labels=None if self.spec_labels is None else self.spec_labels.detach(),
            cluster_s=None if self.cluster_s is None else self.cluster_s.detach().float(),
            cluster_alpha=None if self.cluster_alpha is None else self.cluster_alpha.detach().float(),
            report=rep, lobe=self.lobe,
            gloss_s=None if self.gloss_s is None else self.gloss_s.detach().float(),
            gloss_alpha=None if self.gloss_alpha is None else self.gloss_alpha.detach().float(),
        )

    def to_module(self) -> nn.Module:
        """A trainable module: :class:`PhongModel` (global; :class:`~torchmetal.lobes.LobeModel` for
        another lobe) or :class:`ClusteredPhongModel` (gloss maps: one cluster per pixel)."""
        if self.gloss_s is not None:
            h, w = self.gloss_s.shape[-2:]
            labels = torch.arange(h * w, device=self.gloss_s.device).view(h, w)
            return ClusteredPhongModel(self.texture, labels, self.gloss_s.reshape(3, -1).T, self.gloss_alpha.reshape(3, -1).T,
                                       self.normals, self.size, lobe=self.lobe)
        if self.spec_labels is None:
            if self.lobe != "phong":
                return LobeModel(self.texture, self.s, self.alpha, self.normals, self.size, lobe=self.lobe)
            return PhongModel(self.texture, self.s, self.alpha, self.normals, self.size)
        return ClusteredPhongModel(self.texture, self.spec_labels, self.cluster_s, self.cluster_alpha, self.normals, self.size,
                                   lobe=self.lobe)
