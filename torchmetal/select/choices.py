"""The choices made before the Phong fit, each declared for the harness (:mod:`torchmetal.select.harness`).

They follow one reference fit (:func:`reference_context`): the default Phong fit on a ≤ 128² pixel grid of
the capture makes the coating's own choices once (lobe, specular structure, weights), and every candidate of
the choices below is then fitted with that model — the model the final fit will use — so that a candidate
fit repeats none of them and no candidate is scored against a simpler stand-in (a global lobe on a
two-material sample misfits, and estimated normals, a relief or a moved light then "explain" the misfit),
starting from the reference fit's values (:mod:`torchmetal.fit.start`).

============ ============================= ================ ============================================
choice       candidates (reference first)  error (paired)   screen (skips the test)
============ ============================= ================ ============================================
registration off, shift                    pixel median     every shot within 1 px of the others (untested)
clipping     channel, pixel                block mean       their other channels hold < 10 % of the residual
normals      flat, estimate                pixel median (1) the residual follows no tilt (tilt_screen), or
                                                            tilts explain < 25 % of the typical pixel's
relief       flat, relief                  pixel median (1) as normals, on its downsampled grid; < 50 %
light        off, flash                    pixel median     moving every light gains < 0.5 % in-sample
============ ============================= ================ ============================================

(1) paired by the rule's *typical* pairing (:func:`~torchmetal.select.rule.paired_choice`): a normal map or relief
must be lower on most pixels and lower their errors' geometric mean by :data:`~torchmetal.select.rule.TYPICAL_GAIN`,
not their mean.

The normals' test leaves out one shot at a time (``folds=None``), the others three groups of shots: a normal per
pixel fitted on two thirds of the shots predicts the third far worse than the final fit's normals, fitted on every
shot, predict a new one, so the three-group test missed estimated normals that gained against the truth (a relief
has a few parameters, not two a pixel: its test keeps three groups; docs/measurements.md, ninth session).

The clipping's errors pair up per block of pixels (:func:`~torchmetal.select.harness.block_means`): a misfit
is spatially correlated, and per observation the rule's z overstated it (the random scenes' clipping test took
"pixel" on 24 % of the scenes clipped honestly); its candidates are fitted with the paper's model
(:data:`CLIPPING_FIT`: the one exception, and why). The others pair per pixel, on each pixel's median. A capture's own normal map is kept untested, flat or not. Adding a choice: declare a :class:`Choice` here
and add it to :data:`PREFIT`.
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial
from typing import TYPE_CHECKING

import torch

from torchmetal.clipping import partly_clipped, pixel_clipped
from torchmetal.fit.api import fit_phong
from torchmetal.fit.start import refit_options
from torchmetal.io.grid import strided_capture
from torchmetal.lightcal.estimate import calibrate_positions
from torchmetal.normals.estimate import estimate_normals
from torchmetal.normals.relief import RES, factor_for, fit_normals, fit_relief
from torchmetal.registration import (
    moved,
    registered,
    registration_shifts,
    shifts_against,
    shot_shifts,
    unregistrable,
    valid_observations,
)
from torchmetal.select.harness import Choice, Context, decide, observation_errors, pixel_errors
from torchmetal.select.rule import TYPICAL_GAIN, Decision
from torchmetal.select.screens import clipping_screen, light_screen, tilt_screen

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture

REFERENCE_PIXELS = 128 * 128  # the reference fit's grid
NORMALS_PIXELS = 64 * 64  # per-pixel photometric stereo needs no more to say whether the sample has relief
CLIPPING_PIXELS = 128 * 128  # clipping sits in highlights, a few of its pixels each
LIGHT_PIXELS = 128 * 128
REGISTRATION_GAIN = 0.05  # shots moved back must lower the per-pixel median held-out error by 5 %
CLIPPING_GAIN = 0.005  # dropping data must pay for itself (docs/design.md §4)
LIGHT_GAIN = 0.02  # the flash's move: 2 % (docs/design.md §4)
#: the tilt screen's floor on the typical pixel's explained share (tilt_screen's ``min_explained``): on 200 random
#: scenes no test that took its extension read less than 0.28 (normals) and 0.62 (relief); the relief's floor is
#: the rule's own gain (a relief is a constrained tilt), the normals' half of it (the estimate refits more than a tilt)
NORMALS_EXPLAINED = TYPICAL_GAIN / 2
RELIEF_EXPLAINED = TYPICAL_GAIN


def reference_context(capture: Capture, fit_kwargs: dict) -> Context:
    """The :class:`~torchmetal.select.harness.Context` whose model is the reference fit's on the capture's grid
    (``fit_kwargs``: the fit's own options, ``lobe``/``weights`` "auto" where the final fit chooses them),
    made on first use."""
    keep = {k: fit_kwargs[k] for k in ("scheme", "tol", "max_iters") if k in fit_kwargs}

    def reference(ctx: Context) -> dict:
        grid = strided_capture(capture, REFERENCE_PIXELS)
        fit = fit_phong(grid, **fit_kwargs)
        ctx.keep_reference(grid, fit)
        # gloss maps as the structure they started from: per-pixel gloss is underdetermined on a fold's two thirds
        # of the shots, and a test whose reference candidate is underdetermined takes an extension that merely
        # looks better (docs/measurements.md, seventh session); the final fit decides the maps on every shot
        return {**keep, **refit_options(fit, maps=False)}

    return Context(reference=reference)


def _fit(train: Capture, ctx: Context):
    return ctx.fit(train)


def _render(fit):
    return lambda hold: fit.render(hold.lights, hold.intensities, hold.cameras)


def _reference_screen(screen):
    """A screen of the reference model fitted on the whole grid (the reference fit itself where the grid is its)."""
    return lambda grid, ctx: screen(ctx.fit(grid), grid)


# ----------------------------------------------------------------------------- clipping


def _clipping_untested(capture: Capture, ctx: Context) -> str | None:
    return None if partly_clipped(capture) else "no observation has some but not all channels clipped"


#: the clipping test's model: the paper's. Its error measure cannot see the clipped observations (a left-out
#: shot's are not valid under the channel reading), only how reading them shifted the fit elsewhere; a richer model
#: absorbs that shift where the truth still shows it (zoo sphere_sharp72 with its chosen GGX: held-out gain 0.35 %,
#: under the minimum, and 1.17 dB lost against its truth). A censored residual would let it see them (issue 46)
CLIPPING_FIT = {"lobe": "phong", "specular": "global", "weights": "uniform", "start": None}


def _clipping_fit(train: Capture, candidate: str, ctx: Context):
    return _render(ctx.fit(pixel_clipped(train) if candidate == "pixel" else train, **CLIPPING_FIT))


def _clipping_hold(grid: Capture, group: list[int]) -> Capture:
    """The held-out shots' observations with no channel clipped (valid under either reading), at pixels that some
    training shot saw unclipped in every channel. Elsewhere the "pixel" reading has no training observation of the
    pixel and its texture is a guess: where a phone's processed clip dropped whole pixels from every shot of a fold,
    those guesses alone made the reading that recovers the truth lose the test (random scene 300,
    docs/measurements.md, eighth session)."""
    pc = pixel_clipped(grid)
    train = [k for k in range(grid.num_shots) if k not in group]
    unseen = pc.saturated[train].all(0, keepdim=True)  # (1, 3, H, W): no training shot saw the pixel unclipped
    hold = pc.subset(group)
    return replace(hold, saturated=hold.saturated | unseen)


CLIPPING = Choice(
    "clipping", ("channel", "pixel"), fit=_clipping_fit, errors=observation_errors,
    grid=lambda c: strided_capture(c, CLIPPING_PIXELS), hold=_clipping_hold,
    rule={"min_gain": CLIPPING_GAIN}, untested=_clipping_untested,
    screen=lambda grid, ctx: clipping_screen(ctx.fit(grid, **CLIPPING_FIT), grid), min_shots=3)


# ----------------------------------------------------------------------------- normals


def _given(capture: Capture, ctx: Context) -> str | None:
    return "the capture's own normals (normals.npy)" if capture.normals_given else None


def _normals_fit(train: Capture, candidate: str, ctx: Context):
    if candidate == "estimate":
        train = replace(train, normals=estimate_normals(train, fit_kwargs=ctx.model).normals)
    return _render(_fit(train, ctx))


NORMALS = Choice(
    "normals", ("flat", "estimate"), fit=_normals_fit, errors=pixel_errors,
    grid=lambda c: strided_capture(c, NORMALS_PIXELS), follows=("clipping",),
    rule={"min_gain": TYPICAL_GAIN, "typical": True}, untested=_given,
    screen=_reference_screen(partial(tilt_screen, min_explained=NORMALS_EXPLAINED)), floor=0.0, folds=None)


# ----------------------------------------------------------------------------- relief


def _relief_untested(capture: Capture, ctx: Context) -> str | None:
    if capture.normals_given:
        return "the capture's own normals (normals.npy)"
    if ctx.chosen.get("normals") == "estimate":
        return "estimated normals kept"
    return None


def _relief_fit(train: Capture, candidate: str, ctx: Context):
    if candidate == "relief":  # the heights from the relief's own fit; the rendering model is the final one
        train = replace(train, normals=fit_normals(fit_relief(train), train).to(train.images.dtype))
    return _render(_fit(train, ctx))


def _typical(d: Decision, errors: dict) -> None:
    """A relief that wins must also lower the typical pixel's error (the median of the per-pixel relative
    changes): an embossing shows in every pixel of it, a flake's glint in a few (docs/design.md §4)."""
    if d.chosen != "relief":
        return
    flat, alt = torch.cat(errors["flat"]), torch.cat(errors["relief"])
    seen = ~torch.isnan(flat) & ~torch.isnan(alt) & (flat > 0)
    change = float(((alt[seen] - flat[seen]) / flat[seen]).median()) if bool(seen.any()) else float("inf")
    better = float((alt[seen] < flat[seen]).double().mean()) if bool(seen.any()) else 0.0
    if change >= 0.0:
        d.chosen = "flat"
        d.reason += (f"; but the typical pixel's error does not fall (median change {100 * change:+.1f} %, better on "
                     f"{100 * better:.0f} % of pixels: a few pixels' gain, glints, not a relief): flat kept")
    else:
        d.reason += f"; the typical pixel's error falls too (median change {100 * change:+.1f} %, better on {100 * better:.0f} % of pixels)"


RELIEF = Choice(
    "relief", ("flat", "relief"), fit=_relief_fit, errors=pixel_errors,
    grid=lambda c: c.downsampled(factor_for(c, RES)), follows=("clipping", "normals"),
    rule={"min_gain": TYPICAL_GAIN, "typical": True}, untested=_relief_untested,
    screen=_reference_screen(partial(tilt_screen, min_explained=RELIEF_EXPLAINED)),
    check=_typical, floor=0.0)


# ----------------------------------------------------------------------------- light


def _light_untested(capture: Capture, ctx: Context) -> str | None:
    if not bool((capture.lights[:, 3] > 0).any()):
        return "directional lights only: no falloff or position to calibrate"
    if ctx.model.get("specular") == "none":  # a diffuse-only fit's misfit moves the lights as readily as a misplaced flash
        return "the reference fit kept no specular lobe (no highlight on the grid): capture's lights kept"
    return None


def _light_fit(train: Capture, candidate: str, ctx: Context):
    if candidate == "off":
        return _render(_fit(train, ctx))
    cal, fit = calibrate_positions(train, fit_kwargs=ctx.model, shared=True, first=ctx.fit(train))
    unseen = cal.for_unseen()
    return lambda hold: fit.render(unseen.lights(hold), hold.intensities, hold.cameras) * unseen.factor(hold)


LIGHT = Choice(
    "light", ("off", "flash"), fit=_light_fit, errors=pixel_errors,
    grid=lambda c: strided_capture(c, LIGHT_PIXELS), follows=("clipping", "normals", "relief"),
    rule={"min_gain": LIGHT_GAIN}, untested=_light_untested, screen=_reference_screen(light_screen))


# ----------------------------------------------------------------------------- registration


REGISTRATION_WIDTH = 256  # the test's grid: box-averaged to this width (a shift of 2-30 px at 1 MP stays 0.5-8 px)
REGISTRATION_PX = 1.0  # shots registered within this many (full-size) pixels are not tested: the measurement's accuracy


def _registration_grid(capture: Capture) -> Capture:
    return capture.downsampled(max(1, -(-capture.width // REGISTRATION_WIDTH)))


def _registration_untested(capture: Capture, ctx: Context) -> str | None:
    grid = _registration_grid(capture)
    why = unregistrable(grid)
    if why is not None:
        return why
    f = capture.width / grid.width
    worst = f * shot_shifts(grid.images, valid_observations(grid), max_width=REGISTRATION_WIDTH)["max"]
    return None if worst >= REGISTRATION_PX else f"the shots are registered within {worst:.2f} px (< {REGISTRATION_PX:g})"


def _registration_fit(train: Capture, candidate: str, ctx: Context):
    """"shift": the training shots moved back by their shifts against each other, the model fitted on them; a
    left-out shot's render is moved into its photo's frame by the shot's shift against the registered ones (the
    registration a new photo gets when it is taken), so both candidates are scored on the same photos."""
    if candidate == "off":
        return _render(_fit(train, ctx))
    reg = registered(train, registration_shifts(train, max_width=REGISTRATION_WIDTH))
    fit = _fit(reg, ctx)

    def predict(hold: Capture):
        render = fit.render(hold.lights, hold.intensities, hold.cameras)
        return moved(render, shifts_against(reg.images, hold.images, max_width=REGISTRATION_WIDTH), sign=1.0)

    return predict


REGISTRATION = Choice(
    "registration", ("off", "shift"), fit=_registration_fit, errors=pixel_errors, grid=_registration_grid,
    rule={"min_gain": REGISTRATION_GAIN}, untested=_registration_untested, floor=0.0)


#: the choices before the Phong fit, in the order they are made
PREFIT = (REGISTRATION, CLIPPING, NORMALS, RELIEF, LIGHT)
DEFAULT_FIT = {"lobe": "auto", "weights": "auto"}  # the reference fit's options where a caller gives none


def choose(choice: Choice, capture: Capture, *, fit_kwargs: dict | None = None, chosen: dict | None = None) -> Decision:
    """``choice`` decided on ``capture`` alone (its own reference fit; ``chosen``: the choices it follows), as
    :func:`~torchmetal.pipeline.fit_material` decides it in turn."""
    ctx = reference_context(capture, {**DEFAULT_FIT, **(fit_kwargs or {})})
    ctx.chosen.update(chosen or {})
    return decide(choice, capture, ctx)

__all__ = ["CLIPPING", "DEFAULT_FIT", "LIGHT", "NORMALS", "PREFIT", "REGISTRATION", "RELIEF", "Context", "choose",
           "reference_context"]
