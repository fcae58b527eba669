"""Spatially varying specular: a few clusters, each with its own s, α — kept only when it helps.

Pixels are grouped by k-means on per-pixel colour and specular features (:mod:`torchmetal.fit.cluster_features`).
:func:`choose_specular` fits the global model and K-cluster models (colour, specular or both
feature sets) on all shots but one (on a pixel subsample) and compares their errors on the shot
left out; clustered specular is chosen only when it lowers those errors beyond noise (the paired rule
of :mod:`torchmetal.select.rule`). Clusters without highlight evidence keep the global s, α.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import numpy as np
import torch
from torch import Tensor

from torchmetal.fit.cluster_features import (
    FEATURE_SETS,
    Labeler,
    SpecFeatureMap,
    grid_coords,
    make_labeler,
    spec_feature_map,
)
from torchmetal.fit.problem import Observations, Reference, Weighting, build_observations, weighted
from torchmetal.fit.refine import SpecFit, chunk_model, fit_specular, pinned_terms, spec_sums, texture_map
from torchmetal.select.rule import MIN_GAIN_ABS, Decision, paired_choice

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

EVIDENCE_REL = 1e-3  # the specular term must explain this fraction of the diffuse-only residual…
EVIDENCE_ABS = 1e-6  # …and this fraction of Σ w·y²


def evidence(fit: SpecFit) -> Tensor:
    """(K, 3) bool: the element's specular term explains enough of the residual to be kept."""
    gain = fit.A - fit.cost
    return (fit.s > 0) & (fit.explained() > EVIDENCE_REL) & (gain > EVIDENCE_ABS * fit.Y)


def fit_without_hold(capture: Capture, glob: SpecFit, *, stride: int, hold: int, tol: float, max_iters: int,
                     dtype: torch.dtype, chunk: int, weighting: Weighting | None
                     ) -> tuple[Observations, Observations, SpecFit]:
    """The observations of every shot but ``hold`` (weighted at ``glob``), those of ``hold``, and the
    variable-projection fit on the former from ``glob``'s α: what a single-shot held-out choice scores."""
    n = int(capture.images.shape[0])
    obs = build_observations(capture, stride=stride, shots=[i for i in range(n) if i != hold], dtype=dtype, chunk=chunk,
                             ref=Reference(glob.s, glob.alpha), weighting=weighting, lobe=glob.lobe)
    ho = build_observations(capture, stride=stride, shots=[hold], dtype=dtype, chunk=chunk, lobe=glob.lobe)
    return obs, ho, fit_specular(obs, torch.log(glob.alpha), tol=tol, max_iters=max_iters)


def heldout_evidence(capture: Capture, glob: SpecFit, *, stride: int, hold: int, tol: float, max_iters: int,
                     dtype: torch.dtype, chunk: int, weighting: Weighting | None) -> Decision:
    """Does the specular term predict a shot left out of the fit better than diffuse alone?

    A sharp lobe (α in the thousands) can fit the noise of the few observations nearest the
    mirror direction, so an in-sample gain alone is no evidence on a noisy, highlight-free
    capture. Fit on every shot but ``hold`` (the one with most predicted specular energy) and
    compare the held-out errors by the paired rule. The reference is "specular", the paper's model: s = 0 is
    taken only where diffuse alone predicts the shot better beyond noise. A held-out shot that happens to see
    no highlight (a light error moves it, or no mirror direction falls on the sample) is no evidence against
    one, and dropping the specular term on such a tie cost 3–15 dB against the paper's scheme
    (docs/measurements.md, "specular evidence").
    """
    obs, ho, g = fit_without_hold(capture, glob, stride=stride, hold=hold, tol=tol, max_iters=max_iters, dtype=dtype,
                                  chunk=chunk, weighting=weighting)
    zero = torch.zeros_like(g.s)
    errors = {"specular": heldout_errors(ho, texture_map(obs, g.s, g.eb), g.s, g.alpha),
              "diffuse": heldout_errors(ho, texture_map(obs, zero, g.eb), zero, g.alpha)}
    d = paired_choice("specular evidence", errors, "specular", floor=MIN_GAIN_ABS * mean_square(ho))
    d.holds, d.pixels = [hold], ho.num_pixels
    return d


#: a cluster's s beyond this many times the global lobe's largest s is a lobe its shots saw only in its tail: a cluster
#: whose highlight no fit shot put near its pixels, whose s grows without bound while its tail stays small (on a random
#: scene's 5-shot fold, s 1.5e6 at α 1059, renders of 1e6 on the left-out shots); its pixels keep the global terms
S_RATIO_MAX = 100.0
RUNAWAY_ROUNDS = 3


def runaway(s: Tensor, ref_s: Tensor) -> Tensor:
    """(K, 3) bool: the elements of ``s`` (K, 3) beyond :data:`S_RATIO_MAX` times the largest of ``ref_s``."""
    return s > S_RATIO_MAX * ref_s.max()


def fit_clustered(obs: Observations, labeler: Labeler, glob: SpecFit, *, tol: float, max_iters: int) -> SpecFit:
    """K-cluster fit on ``obs`` (labels set from its T_min); clusters without evidence, or with an s beyond
    :data:`S_RATIO_MAX` times the global one, keep ``glob``."""
    k = labeler.k
    if obs.labels is None:
        raise ValueError("fit_clustered: observations need labels (build them with the labeler)")
    beta0 = torch.log(glob.alpha.expand(k, 3)).clone()
    fit = fit_specular(obs, beta0, tol=tol, max_iters=max_iters)
    pin = ~evidence(fit) | runaway(fit.s, glob.s)
    for _ in range(RUNAWAY_ROUNDS):  # holding some elements can send another's s beyond the bound
        if not bool(pin.any()) or (fit.pinned is not None and bool((pin == fit.pinned).all())):
            break
        s_fix, b_fix = pinned_terms(pin, glob.s.expand(k, 3), glob.alpha.expand(k, 3))
        fit = fit_specular(obs, torch.where(pin, b_fix, torch.log(fit.alpha)), tol=tol, max_iters=max_iters,
                           s_fixed=s_fix, beta_fixed=b_fix)
        fit.pinned = pin
        pin = pin | runaway(fit.s, glob.s)
    return fit


RELABEL_GAIN = 25.0  # a pixel changes cluster when that lowers its cost by > 25 mean per-observation costs (5 σ)
RELABEL_ROUNDS = 2
# relabelling adds no parameter (the same K elements; pixels moved by their in-sample cost, RELABEL_GAIN), so the
# held-out test only guards against harm: a lower held-out MSE (by MIN_GAIN, any z > 0) keeps it
RELABEL_Z = 0.0


def pixel_costs(obs: Observations, s: Tensor, alpha: Tensor) -> Tensor:
    """(K, P) float64: each pixel's least-squares cost (texture in closed form, channels summed)
    under each element's s, α (K, 3) — the variable-projection cost A − 2·s·B + s²·C."""
    labels, obs.labels = obs.labels, None  # every pixel at the one α asked for
    try:
        a = obs.A.double()  # once for every element
        out = []
        for k in range(int(s.shape[0])):
            st = spec_sums(obs, alpha[k].view(1, 3), per_pixel=True)[0]  # (6, 3, P)
            sk = s[k].to(torch.float64).view(3, 1)
            out.append((a - 2.0 * sk * st[0].double() + sk * sk * st[1].double()).sum(0))
    finally:
        obs.labels = labels
    return torch.stack(out)


def relabel(obs: Observations, s: Tensor, alpha: Tensor, per_obs: float) -> tuple[Tensor, int]:
    """New labels (P,) of ``obs``'s pixels and how many moved: a pixel moves to the element of s, α
    (K, 3) that explains it best (:func:`pixel_costs`) when that lowers its cost by more than
    :data:`RELABEL_GAIN` × ``per_obs`` (the fit's mean cost per observation). Per pixel: the same
    labels whichever tiles or chunks the pixels come in."""
    cost = pixel_costs(obs, s, alpha)
    current = cost.gather(0, obs.labels.view(1, -1))[0]
    best, arg = cost.min(0)
    change = (current - best) > RELABEL_GAIN * per_obs
    return torch.where(change, arg, obs.labels), int(change.sum())


def relabel_pixels(obs: Observations, fit: SpecFit,
                   refit: Callable[[Observations, SpecFit], SpecFit]) -> tuple[SpecFit, int]:
    """Move pixels to the cluster whose s, α explain them best, where that is significant, and refit.

    The labeler draws clusters from T_min colour and specular features on a subsample; at a
    material edge (a foil disc on paper) pixels of one material land in the other's cluster and
    their highlight is rendered with the wrong lobe (zoo two_materials: 232 foil pixels in paper
    clusters, 55 % of the held-out error, 3.4 dB below the truth-parameter render; after: 1, and
    within 0.01 dB). See :func:`relabel`: pixels whose shots never see a highlight gain nothing
    and keep their label. ``refit(obs with the new labels, fit)`` → the new :class:`SpecFit`; up
    to :data:`RELABEL_ROUNDS` rounds. Returns (fit, pixels moved).
    """
    moved = 0
    n_obs = obs.n_obs
    for _ in range(RELABEL_ROUNDS):
        labels, n = relabel(obs, fit.s, fit.alpha, float(fit.cost.sum()) / n_obs)
        if n == 0:
            break
        obs.labels = labels
        moved += n
        fit = refit(obs, fit)
    return fit, moved


class LabelMap:
    """A labeler (:func:`~torchmetal.fit.problem.build_observations`) that reads each pixel's label
    from an (H, W) int64 ``.npy`` file — the tiled fit's labels after :func:`relabel`. Picklable."""

    def __init__(self, path: str, k: int) -> None:
        self.path, self.k = str(path), int(k)

    def __call__(self, tmin: Tensor, ij: Tensor) -> Tensor:
        lab = np.load(self.path, mmap_mode="r")
        idx = ij.long().cpu().numpy()
        return torch.from_numpy(np.ascontiguousarray(lab[idx[0], idx[1]])).to(tmin.device)


def mean_square(hold: Observations) -> float:
    """Mean of y² over the valid held-out observations."""
    return float(hold.energy().sum()) / hold.n_obs


def heldout_mse(hold: Observations, texture: Tensor, s: Tensor, alpha: Tensor, labels: Tensor | None) -> float:
    """Mean squared error of rendering the held-out observations with (texture (3, P), s, α (K, 3)).

    The texture is clamped at 0 first, as the material stores it (``fit.api._finish_texture``):
    the variable projection's free texture can go negative under a strong, broad lobe, and a
    held-out test of that unrenderable model kept 4 GGX clusters on the real grey sphere whose
    texture was negative in half their pixels (−5 dB on other light directions)."""
    texture = texture.clamp_min(0.0)
    sse = torch.zeros((), dtype=torch.float64, device=texture.device)
    cnt = 0.0
    for y, w, diffuse, spec in chunk_model(hold, texture, s, alpha, labels):
        r = y - diffuse - spec
        sse += (weighted(r, w) * r).double().sum()
        cnt += float(w.sum())
    return float(sse) / max(cnt, 1.0)


def heldout_errors(hold: Observations, texture: Tensor, s: Tensor, alpha: Tensor, labels: Tensor | None = None) -> Tensor:
    """Squared errors (M,) float64 of the valid held-out observations, in a fixed order (the valid
    set does not depend on the model, so two candidates' errors pair up element by element for
    :func:`~torchmetal.select.rule.paired_choice`). The texture is clamped at 0 as in :func:`heldout_mse`;
    s, α (K, 3) per element, ``labels`` (P,) the fit's pixel labels when K > 1."""
    texture = texture.clamp_min(0.0)
    out = []
    for y, w, diffuse, spec in chunk_model(hold, texture, s, alpha, labels):
        r = y - diffuse - spec
        out.append((r * r)[w > 0].double())
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.float64)


@dataclass
class Selection:
    """Outcome of the held-out comparison: k = 1 means global specular."""

    k: int
    labeler: Labeler | None
    hold: int  # -1: no held-out shot
    mse: dict = field(default_factory=dict)  # "global" / "K=2" … → held-out MSE
    reason: str = ""
    relabel: bool = False  # the full-resolution fit moves pixels between clusters (relabel_pixels)
    decisions: list = field(default_factory=list)  # the Decision records: clusters, then relabelling if tried
    errors: Tensor | None = None  # (M,) the kept candidate's held-out squared errors (what gloss maps must beat)


def _relabel_decision(obs: Observations, ho: Observations, labeler: Labeler, glob: SpecFit, ij: Tensor, name: str,
                      errors: Tensor, *, tol: float, max_iters: int) -> Decision | None:
    """Does :func:`relabel_pixels` lower the held-out errors of the chosen clusters (``name``, ``errors``)
    at all (``RELABEL_Z``)? (Zoo two_materials: yes — its misassigned edge pixels; the real card: no — its
    clusters are not materials, and moving pixels by their in-sample cost lost 0.15 dB held out.)
    None when no pixel moves."""
    obs.labels = labeler(obs.tmin, ij)
    try:
        fit = fit_clustered(obs, labeler, glob, tol=tol, max_iters=max_iters)
        s_fix, b_fix = pinned_terms(fit.pinned, fit.s, fit.alpha)  # clusters without evidence: global terms
        fit, moved = relabel_pixels(obs, fit, lambda o, f: fit_specular(o, torch.log(f.alpha), tol=tol, max_iters=max_iters,
                                                                           s_fixed=s_fix, beta_fixed=b_fix))
        if moved == 0:
            return None
        moved_errors = heldout_errors(ho, texture_map(obs, fit.s, fit.eb), fit.s, fit.alpha, obs.labels)
        d = paired_choice("relabel", {name: errors, "relabel": moved_errors}, name, z_min=RELABEL_Z,
                          floor=MIN_GAIN_ABS * mean_square(ho))
        d.pixels = ho.num_pixels
        return d
    finally:
        obs.labels = None


def choose_specular(
    capture: Capture,
    glob: SpecFit,
    *,
    candidates: tuple[int, ...],
    stride: int,
    hold: int | None,
    force: bool,
    tol: float,
    max_iters: int,
    dtype: torch.dtype,
    chunk: int,
    weighting: Weighting | None,
    seed: int = 0,
    feature_sets: tuple[str, ...] = ("colour", "specular", "both"),
    relabel: bool = True,
) -> Selection:
    """Fit global and K-cluster specular on all shots but ``hold``; keep global unless a clustered
    candidate lowers ``hold``'s errors beyond noise (:func:`~torchmetal.select.rule.paired_choice`).

    ``force`` picks the lowest held-out MSE among the clustered candidates (specular="clustered");
    ``hold=None`` (too few shots) ranks them by in-sample error and always picks one. Otherwise,
    within a feature set, larger K are tried only while the last K beat global's held-out MSE
    (on a sample without clusters that is 3 fits instead of 9). ``relabel``: whether a clustered choice
    tries relabelling its pixels too (:func:`relabel_pixels`).
    """
    n = int(capture.images.shape[0])
    fit_shots = [i for i in range(n) if i != hold]
    ref = Reference(glob.s, glob.alpha)
    obs = build_observations(capture, stride=stride, shots=fit_shots, dtype=dtype, chunk=chunk, ref=ref,
                             weighting=weighting, want_tmin=True, lobe=glob.lobe)
    g = fit_specular(obs, torch.log(glob.alpha), tol=tol, max_iters=max_iters)
    ho, score = _scorer(capture, obs, hold, stride=stride, dtype=dtype, chunk=chunk, lobe=glob.lobe)
    errors = {"global": score(g, None)}
    mse = {"global": float(errors["global"].mean())}
    usable = obs.n.sum(0) > 0
    spec = spec_feature_map(obs, g, stride)
    ij = grid_coords(obs.height, obs.width, stride, obs.device).to(obs.dtype)
    labelers = _cluster_candidates(obs, g, score, errors, mse, ij, usable, spec, candidates=candidates,
                                   feature_sets=feature_sets, stop=not force and ho is not None, seed=seed, tol=tol,
                                   max_iters=max_iters)
    if not labelers:
        return Selection(1, None, hold, mse, "no cluster candidate fits the image", errors=errors["global"])
    best = min(labelers, key=mse.get)
    if ho is None:
        return Selection(labelers[best].k, labelers[best], -1, mse, f"{best}: lowest in-sample error (no shot to hold out)")
    return _held_out_selection(obs, ho, g, ij, labelers, best, errors, mse, hold=hold, force=force, tol=tol,
                               max_iters=max_iters, try_relabel=relabel)


def _scorer(capture: Capture, obs: Observations, hold: int | None, *, stride: int, dtype: torch.dtype, chunk: int,
            lobe: str) -> tuple[Observations | None, Callable[[SpecFit, Tensor | None], Tensor]]:
    """(held-out observations or None, score: (fit, labels) → errors): the held-out shot's squared errors, or
    without one (``hold`` None: no shot to spare) the in-sample error (only to rank candidates when forced)."""
    if hold is None:
        ho = None
        score = lambda fit, labels: torch.full((1,), float(fit.cost.sum()) / obs.n_obs, dtype=torch.float64)  # noqa: E731
    else:
        ho = build_observations(capture, stride=stride, shots=[hold], dtype=dtype, chunk=chunk, lobe=lobe)
        score = lambda fit, labels: heldout_errors(ho, texture_map(obs, fit.s, fit.eb), fit.s, fit.alpha, labels)  # noqa: E731
    return ho, score


def _cluster_candidates(obs: Observations, g: SpecFit, score: Callable[[SpecFit, Tensor | None], Tensor], errors: dict,
                        mse: dict, ij: Tensor, usable: Tensor, spec: SpecFeatureMap, *, candidates: tuple[int, ...],
                        feature_sets: tuple[str, ...], stop: bool, seed: int, tol: float,
                        max_iters: int) -> dict[str, Labeler]:
    """Fit each clustered candidate (feature set, K) from the global fit ``g``; its errors and MSE go into
    ``errors`` and ``mse``. With ``stop``, larger K of a feature set are tried only while the last K beats
    global's MSE. Returns the candidates' labelers by name."""
    labelers: dict[str, Labeler] = {}
    for feats in feature_sets:
        for k in sorted(candidates):
            if k < 2 or k > int(usable.sum()):
                continue
            lab = make_labeler(obs.tmin, ij, usable, k, spec=spec, features=feats, seed=seed)
            obs.labels = lab(obs.tmin, ij)
            if int(obs.labels.unique().numel()) < 2:
                continue
            fit = fit_clustered(obs, lab, g, tol=tol, max_iters=max_iters)
            name = f"{feats}:K={k}"
            errors[name] = score(fit, obs.labels)
            mse[name] = float(errors[name].mean())
            labelers[name] = lab
            if stop and mse[name] >= mse["global"]:
                break  # the coarsest split of these features does not beat global: finer ones are not tried
    obs.labels = None
    return labelers


def _complexity(name: str) -> tuple[int, int]:
    """A specular candidate's complexity: (K, its feature set's place in :data:`FEATURE_SETS`); global is (1, 0)."""
    if name == "global":
        return (1, 0)
    feats, k = name.split(":K=")
    return (int(k), list(FEATURE_SETS).index(feats))


def _held_out_selection(obs: Observations, ho: Observations, g: SpecFit, ij: Tensor, labelers: dict[str, Labeler],
                        best: str, errors: dict, mse: dict, *, hold: int, force: bool, tol: float,
                        max_iters: int, try_relabel: bool = True) -> Selection:
    """Global unless a clustered candidate lowers the held-out errors beyond noise (``force``: the ``best``
    candidate then); for a clustered choice, whether relabelling the pixels helps too."""
    d = paired_choice("specular clusters", errors, "global", floor=MIN_GAIN_ABS * mean_square(ho),
                      rank={k: _complexity(k) for k in errors})
    d.holds, d.pixels = [hold], ho.num_pixels
    if force and d.chosen == "global":
        d.chosen = best
        d.reason = f"forced (specular='clustered'): {best}, the lowest held-out MSE among clusters; {d.reason}"
    if d.chosen == "global":
        return Selection(1, None, hold, mse, f"held-out shot {hold}: {d.reason}", decisions=[d], errors=errors["global"])
    chosen = d.chosen
    rel = _relabel_decision(obs, ho, labelers[chosen], g, ij, chosen, errors[chosen], tol=tol,
                            max_iters=max_iters) if try_relabel else None
    decisions = [d] if rel is None else [d, rel]
    relabel = rel is not None and rel.chosen == "relabel"
    if rel is not None:
        rel.holds = [hold]
        mse["relabel"] = rel.mse["relabel"]
    return Selection(labelers[chosen].k, labelers[chosen], hold, mse, f"held-out shot {hold}: {d.reason}"
                     + ("; pixels relabelled" if relabel else ""), relabel=relabel, decisions=decisions,
                     errors=errors[chosen])
