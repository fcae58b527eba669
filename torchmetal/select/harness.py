"""The one harness every choice made before the Phong fit runs through.

A choice is declared (:class:`Choice`): its name, its candidates (the simplest first: the reference, kept
unless another predicts left-out shots better beyond noise), how a candidate is fitted on a set of shots, its
error measure, the pixel grid it is decided on, the choices it follows, and a cheap screen. The harness
(:func:`decide`) owns the rest, the same for every choice:

1. untested cases (the choice's own reason, too few shots) keep the reference and say why;
2. the screen reads the reference fit's residuals on the grid (:mod:`torchmetal.select.screens`); where it
   says the extension cannot matter, the reference is kept without a candidate fit;
3. the shots are dealt into groups (:func:`~torchmetal.select.plan.shot_groups`); for each, every candidate is
   fitted on the other shots **with the model the final fit will use** (``Context.model``: the lobe, specular
   structure and weights the reference fit chose, so no candidate fit makes those choices again) and renders
   the group; the errors (per pixel, or per block of pixels: :func:`block_means`) pair up across candidates and
   the paired rule (:func:`~torchmetal.select.rule.paired_choice`)
   decides on all groups so far;
4. futility: once every extension predicts worse beyond noise (z below −:data:`FUTILE_Z`) or, under the rule's
   typical pairing, cannot reach its gain (:func:`_futile`), the remaining groups are not fitted;
5. the :class:`~torchmetal.select.rule.Decision` record, with the screen's reading, the rule's outcome after each
   group (``scores["folds"]``: chosen, z and MSE on the groups so far) and the seconds it took.

There is no early stop for a winner: a first group's z overstates what the next groups (other shots, other lights)
show; on random scenes two flash moves at z 20 after one group (twice their bar) were "off" once all three were in
(docs/measurements.md).
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable

import torch
from torch import Tensor

from torchmetal.fit.api import fit_phong
from torchmetal.fit.holdout import valid_mean_square, valid_pixels
from torchmetal.select.plan import shot_groups
from torchmetal.select.rule import MIN_GAIN_ABS, Decision, paired_choice

if TYPE_CHECKING:
    from torchmetal.fit.result import FitResult
    from torchmetal.io.capture import Capture

#: the futility stop's bar: an extension worse by more than the smallest calibrated z (select.rule.CALIBRATED_Z's
#: floor) on the groups so far is not fitted on the rest. Its own calibrated z would rarely stop (clipping 30):
#: the later groups would have to outweigh a loss beyond noise by that z to take the extension (docs/measurements.md)
FUTILE_Z = 4.0
#: the typical rule's futility margin: a fold's standard error understates how much the next fold (other shots, other
#: lights) can differ, so the bar must be out of reach by twice the usual margin (at 4 four more recorded decisions
#: changed, at 8 one)
FUTILE_SE = 8.0
Predict = Callable[["Capture"], Tensor]  # a fitted candidate: held-out shots (M shots) → its render (M, 3, H, W)


@dataclass(frozen=True)
class Screen:
    """A screen's verdict: whether the candidates' test runs, why, and what it read."""

    run: bool
    reason: str
    reading: dict = field(default_factory=dict)


@dataclass
class Context:
    """What every test is given.

    Attributes:
        reference: ``reference(ctx)`` fits the reference model on first use and returns its
            :func:`~torchmetal.fit.fit_phong` options (lobe, specular structure, cluster count, weights, tol,
            max_iters): the model the final fit will use, chosen once (:func:`torchmetal.select.choices.reference_context`).
            A capture whose choices all stay untested never pays for it.
        chosen: the choices made so far (name → chosen candidate), for the ones a choice follows.
        seconds: what the reference fit cost, once made.
        fits: the model's fits by the data they were fitted to and the options changed (:func:`content_key`): a
            fit of the same shots on the same grid is made once, whichever choice asks for it (the reference
            candidate of every choice whose grid is the same: on a capture small enough to be its own grid, the
            registration's, normals', relief's and light's folds are one set of fits), and a screen on the
            reference's grid reuses the reference fit.
        reference_key: the identity (:func:`capture_key`) of the capture the reference fit was made on: the final
            fit reuses it where that was the whole, unchanged capture.
        reference_result: the reference fit itself, once made.
    """

    reference: Callable[[Context], dict]
    chosen: dict = field(default_factory=dict)
    seconds: float = 0.0
    fits: dict = field(default_factory=dict)
    reference_key: tuple | None = None
    reference_result: FitResult | None = None
    _reference_capture: Capture | None = None
    _model: dict | None = None

    @classmethod
    def fixed(cls, model: dict) -> Context:
        """A context whose model is given."""
        return cls(reference=lambda ctx: dict(model))

    @property
    def resolved(self) -> bool:
        return self._model is not None

    @property
    def model(self) -> dict:
        if self._model is None:
            t0 = time.perf_counter()
            self._model = self.reference(self)
            self.seconds = time.perf_counter() - t0
        return self._model

    def keep_reference(self, capture: Capture, fit) -> None:
        """Remember ``fit``, which made the model's choices, as the model's fit of ``capture``; the capture is kept
        alive with it (its tensors' addresses, :func:`capture_key`, are then not reused by another)."""
        self.fits[(content_key(capture), ())] = fit
        self.reference_key, self.reference_result, self._reference_capture = capture_key(capture), fit, capture

    def fit(self, capture: Capture, **changes) -> FitResult:
        """The model fitted to ``capture`` (``fit_phong(capture, **model, **changes)``), once per data and changes."""
        key = (content_key(capture), tuple(sorted(changes.items())))
        if key not in self.fits:
            model = self.model
            if key not in self.fits:  # the reference fit may be this very capture's
                self.fits[key] = fit_phong(capture, **{**model, **changes})
        return self.fits[key]

    def reference_fit(self, capture: Capture):
        """The reference fit where it was made on ``capture`` itself (unchanged, not a grid of it), else None."""
        return self.reference_result if self.resolved and capture_key(capture) == self.reference_key else None


CONTENT_FIELDS = ("images", "saturated", "normals", "mask", "lights", "intensities", "cameras")


def capture_key(capture: Capture) -> tuple:
    """Identifies a capture object's data without reading it: the storage, shape and strides of its tensors, its
    surface size (the final fit asks whether its capture is the one the reference fit was made on, at full size)."""
    parts = [capture.size]
    for name in CONTENT_FIELDS:
        t = getattr(capture, name)
        parts.append((t.data_ptr(), tuple(t.shape), tuple(t.stride()), str(t.dtype), str(t.device)))
    return tuple(parts)


def content_key(capture: Capture) -> tuple:
    """Identifies a capture's data by its values: a digest of its tensors' bytes, shapes and dtypes and its surface
    size. Two grids or shot subsets of a capture made apart (a copy each time: a strided grid's normals, a
    subset's shots) have the same key where they hold the same data. Read in full: meant for the choices' grids."""
    h = hashlib.blake2b(digest_size=16)
    h.update(repr((tuple(capture.size), capture.color_space, capture.normals_given)).encode())
    for name in CONTENT_FIELDS:
        t = getattr(capture, name).detach()
        h.update(repr((name, tuple(t.shape), str(t.dtype))).encode())
        h.update(t.cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return (h.hexdigest(),)


@dataclass(frozen=True)
class Choice:
    """A choice declared (module docstring).

    Attributes:
        name: the Decision's name.
        candidates: the reference first, then its extensions.
        fit: ``fit(train, candidate, ctx)`` → a :data:`Predict` for held-out shots, or None where the candidate
            cannot be tested on these shots (the test then keeps the reference: an abstention).
        errors: ``errors(render, hold)`` → (M,) float64 errors that pair up across candidates (NaN: unseen).
        grid: the capture the test runs on (a pixel grid or a downsampled copy).
        hold: ``hold(grid, group)`` → the held-out shots as scored (default ``grid.subset(group)``).
        follows: the choices made before this one (their outcome is in ``Context``).
        rule: :func:`~torchmetal.select.rule.paired_choice` options (``z_min``, ``min_gain``).
        untested: ``untested(capture, ctx)`` → a reason to keep the reference without a test, or None.
        screen: ``screen(grid, ctx)`` → :class:`Screen` (None: always tested).
        check: ``check(decision, errors)`` may overrule the rule's outcome (and says so in the reason).
        folds: shot groups left out in turn (None: every shot alone, leave-one-out); min_shots: fewer shots keep
            the reference untested.
        floor: the rule's absolute floor as a fraction of the held-out signal's mean square (rounding noise).
    """

    name: str
    candidates: tuple[str, ...]
    fit: Callable[..., Predict | None]
    errors: Callable[[Tensor, Capture], Tensor]
    grid: Callable[[Capture], Capture]
    hold: Callable[[Capture, list[int]], Capture] | None = None
    follows: tuple[str, ...] = ()
    rule: dict = field(default_factory=dict)
    untested: Callable[[Capture, Context], str | None] | None = None
    screen: Callable[[Capture, Context], Screen] | None = None
    check: Callable[[Decision, dict], None] | None = None
    folds: int | None = 3
    min_shots: int = 4
    floor: float = MIN_GAIN_ABS

    @property
    def reference(self) -> str:
        return self.candidates[0]


def kept(choice: Choice, reason: str, **extra) -> Decision:
    """The reference kept without a test, and why."""
    return Decision(choice.name, choice.candidates, choice.reference, reference=choice.reference, reason=reason, **extra)


def decide(choice: Choice, capture: Capture, ctx: Context) -> Decision:
    """Run ``choice`` on ``capture`` (module docstring); the Decision's ``seconds`` is its whole cost."""
    t0 = time.perf_counter()
    d = _decide(choice, capture, ctx)
    d.seconds = time.perf_counter() - t0
    return d


def _decide(choice: Choice, capture: Capture, ctx: Context) -> Decision:
    n = capture.num_shots
    reason = choice.untested(capture, ctx) if choice.untested is not None else None
    if reason is None and n < choice.min_shots:
        reason = f"a left-out test of the {choice.name} needs >= {choice.min_shots} shots, found {n}"
    if reason is not None:
        return kept(choice, reason)
    grid = choice.grid(capture)
    screen = choice.screen(grid, ctx) if choice.screen is not None else None
    scores = {"screen": {"run": screen.run, "reason": screen.reason, **screen.reading}} if screen else {}
    if screen is not None and not screen.run:
        return kept(choice, f"not tested: {screen.reason}", scores=scores)
    groups = shot_groups(n, n if choice.folds is None else choice.folds)
    errors: dict[str, list[Tensor]] = {c: [] for c in choice.candidates}
    rule = dict(choice.rule)
    d = None
    trail: list[dict] = []  # the rule's outcome on the groups so far, after each
    for i, group in enumerate(groups):
        train = grid.subset([k for k in range(n) if k not in group])
        hold = choice.hold(grid, list(group)) if choice.hold is not None else grid.subset(list(group))
        preds = {c: choice.fit(train, c, ctx) for c in choice.candidates}
        if any(p is None for p in preds.values()):
            return kept(choice, f"a candidate could not be tested without shots {list(group)} "
                                f"({', '.join(c for c, p in preds.items() if p is None)}): {choice.reference} kept",
                        scores=scores, holds=groups[: i + 1])
        for c, predict in preds.items():
            with torch.no_grad():
                errors[c].append(choice.errors(predict(hold), hold))
        d = _paired(choice, errors, rule, grid)
        if choice.check is not None:
            choice.check(d, errors)
        trail.append({"chosen": d.chosen, "z": dict(d.z), "mse": dict(d.mse)})
        if i + 1 < len(groups) and all(_futile(d, c, rule) for c in d.z):
            d.reason += (f"; stopped after {i + 1} of {len(groups)} shot groups (every extension worse beyond noise, "
                         f"or short of the typical rule's gain)")
            groups = groups[: i + 1]
            break
    d.holds = groups
    d.pixels = int(grid.height * grid.width)
    d.scores.update(scores, folds=trail)
    return d


def _futile(d: Decision, candidate: str, rule: dict) -> bool:
    """Whether ``candidate`` cannot win on the groups to come: worse beyond noise (z below −:data:`FUTILE_Z`), or,
    under the typical rule, its geometric gain short of the rule's bar by :data:`FUTILE_SE` standard errors of
    its mean log ratio (the normals' and relief's tests: on the recorded tests of random seeds 200–399 this stops
    280 of 324 before their last fold, against 141, and changes one decision more; docs/measurements.md)."""
    if d.z[candidate] < -FUTILE_Z:
        return True
    lr = d.scores.get("log_ratio", {}).get(candidate) if rule.get("typical") else None
    return lr is not None and lr["mean"] + FUTILE_SE * lr["se"] < -math.log1p(-rule["min_gain"])


def _paired(choice: Choice, errors: dict[str, list[Tensor]], rule: dict, grid: Capture) -> Decision:
    """The paired rule on the groups' errors so far, over the observations every candidate saw."""
    cat = {c: torch.cat(e) for c, e in errors.items()}
    seen = ~torch.isnan(torch.stack(list(cat.values()))).any(0)
    floor = choice.floor * valid_mean_square(grid) if choice.floor else 0.0
    return paired_choice(choice.name, {c: e[seen] for c, e in cat.items()}, choice.reference,
                         **{"floor": floor, **rule})


BLOCKS = 64  # blocks a side of the pairing (at most): the paired errors are block means (block_means)
MAX_BLOCK = 8  # pixels a side of a block, at most


def block_means(values: Tensor, valid: Tensor) -> Tensor:
    """(B,) float64: the mean of ``values`` over ``valid`` per square block of pixels (``values``, ``valid``:
    (..., H, W), every leading entry of a pixel in its block; NaN for a block without a valid value).

    Why blocks: the candidates' errors are paired, and the rule's z is the mean paired difference over its standard
    error. A model's misfit is spatially correlated (a misplaced highlight, a material's edge), so per observation
    or per pixel the differences are not independent and z overstates the evidence: the zoo's two_materials took a
    per-pixel clipping reading at z 4.1 per observation and lost 0.44 dB against its truth. Block means are close
    to independent where blocks are wider than the misfit's correlation; a side of ~1/16 of the grid, 1 to 8 px,
    keeps ≥ 256 blocks on the choices' grids."""
    h, w = values.shape[-2:]
    side = max(1, min(MAX_BLOCK, min(h, w) // BLOCKS))
    gh, gw = -(-h // side), -(-w // side)
    rows = torch.arange(h, device=values.device) // side
    cols = torch.arange(w, device=values.device) // side
    ids = (rows[:, None] * gw + cols[None, :]).expand_as(values)
    v = valid.expand_as(values)
    sums = torch.zeros(gh * gw, dtype=torch.float64, device=values.device).index_add_(0, ids[v], values[v].double())
    counts = torch.zeros(gh * gw, dtype=torch.float64, device=values.device).index_add_(
        0, ids[v], torch.ones_like(values[v], dtype=torch.float64))
    return torch.where(counts > 0, sums / counts.clamp_min(1), torch.full_like(sums, math.nan))


def observation_errors(pred: Tensor, hold: Capture) -> Tensor:
    """(B,) float64: per block of pixels (:func:`block_means`), the mean squared error over ``hold``'s valid
    observations in it (every shot and channel)."""
    return block_means((pred - hold.images).double().square(), valid_pixels(hold))


def pixel_errors(pred: Tensor, hold: Capture) -> Tensor:
    """(P,) float64: per mask pixel, the median over ``hold``'s valid observations (shots × channels) of the
    squared error; NaN where the pixel has none. The median, not the mean: a surface's shape or a light's
    place shows in every shot of a pixel, a glint in one (docs/design.md §4). Paired per pixel, not per block
    (:func:`block_means`): a normal map's gain sits where the surface is steep, and block means of it are
    heavy-tailed enough that a bumpy sample's estimate (−13.5 % held-out error) fell to z 2.2; the median already
    damps the spatially correlated misfit that per-observation pairing counted many times over."""
    v = valid_pixels(hold)
    sq = torch.where(v, (pred - hold.images).double() ** 2, torch.full_like(pred, math.nan, dtype=torch.float64))
    inside = hold.mask.reshape(-1).bool()
    return sq.permute(1, 0, 2, 3).reshape(-1, sq.shape[-2] * sq.shape[-1])[:, inside].nanmedian(0).values
