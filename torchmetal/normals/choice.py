"""``normals="auto"``: estimated normals for a capture without a normal map, kept when shots left out of
the fit prefer them.

A capture with given normals (its ``normals.npy``) keeps them. Without, the choice is made on a
pixel grid of the capture (:func:`strided_capture`, ≤ ``PIXELS`` pixels; per-pixel photometric stereo
needs no more to say whether the sample has relief): the shots are dealt into up to ``FOLDS`` groups,
and for each group a fit (:func:`~torchmetal.fit.fit_phong`, its default specular structure) on the other
shots with flat normals, and the same after :func:`~torchmetal.normals.estimate.estimate_normals` on those
shots, render the group. Per pixel, the median squared error over the group's observations
(:func:`pixel_errors`: the shape shows in every shot, a glint in one) pairs up pixel by pixel, and
:func:`~torchmetal.fit.decision.paired_choice` keeps the flat plane unless the estimate lowers them beyond
noise and by ``MIN_GAIN`` (5 %: a normal map is two parameters a pixel). The groups are scored in turn,
and the test stops early (futility) when the estimate already predicts worse beyond noise (z < −z_min): a
flat sample saves the other groups' fits, two thirds of the choice's time.

Where flat is kept, :func:`choose_relief` tests an embossing's relief against it in the same way
(:mod:`~torchmetal.normals.relief`: a height field on 64 control points a side without its slow tilts, which
absorb the lights' errors), on the capture downsampled to ≤ 128², kept only where the typical pixel gains too.

The fits have the default specular structure, not one global lobe: a global lobe misfits a sample of two
materials, and estimated normals that bend its highlights would then win the test (docs/design.md §4).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from torchmetal.fit.api import fit_phong
from torchmetal.fit.decision import Z_MIN, Decision, paired_choice
from torchmetal.fit.holdout import valid_pixels
from torchmetal.fit.shot_plan import shot_groups
from torchmetal.normals.estimate import estimate_normals
from torchmetal.normals.relief import RES, factor_for, fit_relief, render_heldout

if TYPE_CHECKING:
    from torchmetal.fit.result import FitResult
    from torchmetal.io.capture import Capture

PIXELS = 64 * 64  # the decision's pixel grid
FOLDS = 3  # shot groups left out in turn
MIN_SHOTS = 4  # the estimate needs 3 shots besides a left-out one
MIN_GAIN = 0.05  # a normal map (2 parameters a pixel) must lower the per-pixel median held-out error by 5 % (0.2 dB)


def stride_grid(h: int, w: int, max_pixels: int = PIXELS) -> tuple[slice, slice, float, float]:
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


def strided_capture(capture: Capture, max_pixels: int = PIXELS) -> Capture:
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


def pixel_errors(fit: FitResult, hold: Capture) -> Tensor:
    """(P,) float64: per mask pixel, the median over ``hold``'s valid observations (shots × channels) of the
    squared error of rendering them with ``fit``; NaN where the pixel has none.

    The median, not the mean: the question is the surface's shape, which every shot of a pixel shows, and
    a flake sample's glints are single bright observations. Its glinting pixels are tilted mirrors, and
    per-pixel normals fitted to them predict their glints in other shots: with the mean, a flat flake sample
    would take the estimate and carry its glints in the normals (docs/design.md §4)."""
    with torch.no_grad():
        pred = fit.render(hold.lights, hold.intensities, hold.cameras)
    return rendered_pixel_errors(pred, hold)


def rendered_pixel_errors(pred: Tensor, hold: Capture) -> Tensor:
    """:func:`pixel_errors` of a render ``pred`` (N, 3, H, W) of ``hold``'s shots."""
    v = valid_pixels(hold)
    sq = torch.where(v, (pred - hold.images).double() ** 2, torch.full_like(pred, math.nan, dtype=torch.float64))
    inside = hold.mask.reshape(-1).bool()
    return sq.permute(1, 0, 2, 3).reshape(-1, sq.shape[-2] * sq.shape[-1])[:, inside].nanmedian(0).values


def choose_normals(capture: Capture, *, fit_kwargs: dict | None = None, max_pixels: int = PIXELS, folds: int = FOLDS,
                   **rule: float) -> tuple[str, Decision]:
    """"given" for a capture with normals; else "estimate" or "flat", decided on left-out shots (module
    docstring). ``rule``: :func:`~torchmetal.fit.decision.paired_choice`'s ``z_min`` / ``min_gain``.

    Returns:
        (mode, the :class:`~torchmetal.fit.decision.Decision` behind it).
    """
    untested = _untested(capture, "normals", "estimate", "estimated normals")
    if untested is not None:
        return untested
    fit_kwargs = dict(fit_kwargs or {})
    sub = strided_capture(capture, max_pixels)

    def group_errors(train: list[int], group: list[int]) -> tuple[Tensor, Tensor]:
        fit_on, hold = sub.subset(train), sub.subset(group)
        est = estimate_normals(fit_on, fit_kwargs=fit_kwargs)
        return (pixel_errors(fit_phong(fit_on, **fit_kwargs), hold),
                pixel_errors(fit_phong(replace(fit_on, normals=est.normals), **fit_kwargs), hold))

    d = _grouped_test(capture.num_shots, folds, "estimate", group_errors, rule)
    d.pixels = int(sub.images.shape[-2] * sub.images.shape[-1])
    return d.chosen, d


def choose_relief(capture: Capture, *, res: int = RES, folds: int = FOLDS, **rule: float) -> tuple[str, Decision]:
    """"relief" or "flat" for a capture without normals, decided on left-out shots
    (:mod:`~torchmetal.normals.relief`): on the capture box-downsampled to ≤ ``res`` pixels a side, the
    shots dealt into groups as for the estimate; for each group the flat plane and the relief, both with
    global Phong terms fitted on the other shots, render it; per pixel the median squared error over its
    observations, the paired rule with ``MIN_GAIN`` and the same futility stop as :func:`choose_normals`, and
    the typical pixel must gain too (:func:`_typical`).

    Returns:
        (mode, the :class:`~torchmetal.fit.decision.Decision` behind it).
    """
    untested = _untested(capture, "relief", "relief", "a relief")
    if untested is not None:
        return untested
    ds = capture.downsampled(factor_for(capture, res))

    def group_errors(train: list[int], group: list[int]) -> tuple[Tensor, Tensor]:
        fit_on, hold = ds.subset(train), ds.subset(group)
        flat = fit_relief(fit_on, relief=False)
        return tuple(rendered_pixel_errors(render_heldout(f, fit_on, hold), hold)
                     for f in (flat, fit_relief(fit_on, start=flat)))

    d = _grouped_test(capture.num_shots, folds, "relief", group_errors, rule, check=_typical)
    d.pixels = ds.height * ds.width
    return d.chosen, d


def _untested(capture: Capture, name: str, alt: str, what: str) -> tuple[str, Decision] | None:
    """The choice without a test: "given" for a capture with normals, "flat" with too few shots; else None."""
    n = capture.num_shots
    if not capture.flat:
        return "given", Decision(name, ("given",), "given", reason="the capture's own normals (normals.npy)")
    if n < MIN_SHOTS:
        return "flat", Decision(name, ("flat", alt), "flat", reason=f"a left-out test of {what} needs >= {MIN_SHOTS} shots, found {n}")
    return None


def _grouped_test(n: int, folds: int, alt: str, group_errors, rule: dict, check=None) -> Decision:
    """Flat against ``alt`` over the shot groups in turn: ``group_errors(train, group)`` → per-pixel held-out
    errors (flat, alt) of fits on ``train`` rendering ``group``; the paired rule on all groups so far
    (``check(decision, errors)`` may overrule it), stopping early (futility) once ``alt`` predicts worse
    beyond noise: only the remaining groups outweighing them could make it win."""
    groups = shot_groups(n, folds)
    errors: dict[str, list[Tensor]] = {"flat": [], alt: []}
    rule = {"min_gain": MIN_GAIN, **rule}
    for i, group in enumerate(groups):
        flat, other = group_errors([k for k in range(n) if k not in group], list(group))
        errors["flat"].append(flat)
        errors[alt].append(other)
        d = _decide(errors, rule, alt)
        if check is not None:
            check(d, errors)
        if i + 1 < len(groups) and d.z[alt] < -rule.get("z_min", Z_MIN):
            d.reason += f"; stopped after {i + 1} of {len(groups)} shot groups (the {alt} worse beyond noise)"
            groups = groups[: i + 1]
            break
    d.holds = groups
    return d


def _typical(d: Decision, errors: dict[str, list[Tensor]]) -> None:
    """A relief that wins must also lower the typical pixel's error (the median of the per-pixel relative
    changes): an embossing shows in every pixel of it, a flake's glint in a few. Measured: yellow_box's relief
    is better on 54 % of the pixels (median change −9 %); on test_pipeline's flat flake captures, whose
    reliefs won by 16–18 % (z 6.4) and then carried the glints, on 32–33 % (median change +23 to +29 %)."""
    if d.chosen != "relief":
        return
    flat, alt = torch.cat(errors["flat"]), torch.cat(errors["relief"])
    seen = ~torch.isnan(flat) & ~torch.isnan(alt) & (flat > 0)
    change = float(((alt[seen] - flat[seen]) / flat[seen]).median()) if bool(seen.any()) else math.inf
    better = float((alt[seen] < flat[seen]).double().mean()) if bool(seen.any()) else 0.0
    if change >= 0.0:
        d.chosen = "flat"
        d.reason += (f"; but the typical pixel's error does not fall (median change {100 * change:+.1f} %, better on "
                     f"{100 * better:.0f} % of pixels: a few pixels' gain, glints, not a relief): flat kept")
    else:
        d.reason += f"; the typical pixel's error falls too (median change {100 * change:+.1f} %, better on {100 * better:.0f} % of pixels)"


def _decide(errors: dict[str, list[Tensor]], rule: dict, other: str = "estimate") -> Decision:
    """The paired rule on the per-pixel errors of the shot groups so far (pixels seen by both candidates):
    the flat plane against ``other``."""
    flat, alt = torch.cat(errors["flat"]), torch.cat(errors[other])
    seen = ~torch.isnan(flat) & ~torch.isnan(alt)  # pixels with a valid held-out observation (the same for both)
    name = "normals" if other == "estimate" else other
    return paired_choice(name, {"flat": flat[seen], other: alt[seen]}, ref="flat", **rule)
