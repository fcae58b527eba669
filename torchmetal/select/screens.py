"""Cheap screens: can an extension matter at all, read from the reference fit's residuals on the test's grid?

A screen fits no candidate. It asks whether the extension's first step away from the reference would
explain more of the reference fit's residual than noise does; where it would not, the left-out test cannot
find a gain beyond noise either, and its candidate fits are not run.

- :func:`tilt_screen` (normals, relief): per pixel, the residual's projection on the derivative of the render
  with respect to tilting the pixel's normal (two directions; the texture's own direction projected out, as the
  texture is re-solved by any fit). Under the reference (the surface flat, the model right) the explained share
  of a pixel's residual follows an F(2, m − 5) law, m its valid observations, so each pixel gets an exact
  p-value; the screen passes when more pixels than :data:`TILT_SHARE` reach p < :data:`TILT_P` (1 % by chance).
  An embossing, a bump or a lobe that misfits the surface shape lifts that share far above it. Significance is
  not size: the tests' typical rule asks the typical pixel's held-out error to halve, so the screen also asks
  the tilts to explain a share of the typical (median) pixel's residual in-sample — each test its own floor
  (``min_explained``), calibrated on the random scenes (:mod:`torchmetal.select.choices`).
- :func:`clipping_screen`: the share of the reference fit's squared residual that sits on the unclipped
  channels of partly clipped observations. Reading them per pixel drops exactly those; where they hold less
  than the test's minimum gain (:data:`torchmetal.select.choices.CLIPPING_GAIN`) of the residual, they pull the
  fit too little for dropping them to lower a left-out shot's error by that much. The test's calibrated z asks
  far more than that minimum: on 200 random scenes it took "pixel" only where they held 27 % or more, so the
  screen asks for :data:`CLIPPING_SHARE`, under half of that.
- :func:`light_screen` (the flash's move): the in-sample squared error the reference's material, held fixed,
  loses when every point light moves alike (:func:`~torchmetal.lightcal.positions.fit_offsets`, a few LM steps).
  The left-out test asks for :data:`torchmetal.select.choices.LIGHT_GAIN` of held-out error; a move that cannot
  lower the fitted shots' error by :data:`LIGHT_SHARE` of it will not lower a left-out shot's by more.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.fit.holdout import valid_pixels
from torchmetal.lightcal.positions import fit_offsets, move_capture
from torchmetal.select.harness import Screen

if TYPE_CHECKING:
    from torchmetal.fit.result import FitResult
    from torchmetal.io.capture import Capture

TILT_EPS = 1e-3  # the normals' tilt (radians) of the render's central differences
TILT_P = 0.01  # a pixel's p-value below which its residual follows the tilt beyond noise
TILT_SHARE = 0.03  # share of such pixels above which the normals' tests run (1 % by chance alone)
CLIPPING_SHARE = 0.1  # share of the residual on the partly clipped observations' other channels for the test to run
LIGHT_SHARE = 0.005  # in-sample error share the flash's move must gain for its test to run
LIGHT_ITERS = 4  # LM steps of the screen's move (the test's estimate takes more)


def _render(fit: FitResult, capture: Capture, **changes) -> Tensor:
    f = replace(fit, **changes) if changes else fit
    with torch.no_grad():
        return f.render(capture.lights, capture.intensities, capture.cameras).double()


def _tilted(normals: Tensor, axis: int, eps: float) -> Tensor:
    """(3, H, W) the normals tilted by ``eps`` radians towards the x (axis 0) or y (axis 1) direction."""
    t = torch.zeros_like(normals)
    t[axis] = eps
    return F.normalize(normals + t, dim=0)


def tilt_screen(fit: FitResult, capture: Capture, *, min_explained: float = 0.0) -> Screen:
    """The normals' screen (module docstring) of ``fit``, the reference fitted to ``capture``; ``min_explained``:
    the share of the median pixel's residual its two tilts must explain in-sample for the test to run."""
    y = capture.images.double()
    base = _render(fit, capture)
    # observations weighted by the inverse of a variance that grows with the value (shot noise; the 8-bit sRGB step
    # grows with it too): unweighted, a highlight's larger noise lines up with its larger tilt derivative and
    # reads as a tilt (the zoo's 8-bit photo_srgb8, flat: 4.4 % of pixels at p < 0.01; weighted: see TILT_SHARE)
    valid = valid_pixels(capture)
    level = base[valid].clamp_min(0).mean() if bool(valid.any()) else base.new_tensor(1.0)
    v = valid.double() / (level + base.clamp_min(0)).sqrt()  # the square root of the weight, on each residual
    r = (y - base) * v
    n = fit.normals.double()
    jac = [(_render(fit, capture, normals=_tilted(n, a, TILT_EPS).to(fit.normals.dtype))
            - _render(fit, capture, normals=_tilted(n, a, -TILT_EPS).to(fit.normals.dtype))) / (2 * TILT_EPS) * v
           for a in (0, 1)]
    # the texture's direction: the diffuse shading per channel, projected out of each tilt derivative (per pixel
    # and channel, over the shots) since any fit re-solves the texture
    shade = (_render(fit, capture, texture=torch.ones_like(fit.texture)) - _render(fit, capture, texture=torch.zeros_like(fit.texture))) * v
    ss = shade.square().sum(0).clamp_min(1e-300)
    jac = [j - shade * ((j * shade).sum(0) / ss) for j in jac]
    a11, a12, a22 = (jac[0] ** 2).sum((0, 1)), (jac[0] * jac[1]).sum((0, 1)), (jac[1] ** 2).sum((0, 1))
    b1, b2 = (jac[0] * r).sum((0, 1)), (jac[1] * r).sum((0, 1))
    det = a11 * a22 - a12 * a12
    ok = det > 1e-12 * (a11 * a22).clamp_min(1e-300)
    gain = torch.where(ok, (a22 * b1 * b1 - 2 * a12 * b1 * b2 + a11 * b2 * b2) / det.clamp_min(1e-300), torch.zeros_like(det))
    sse = r.square().sum((0, 1))
    dof = valid.double().sum((0, 1)) - 5.0  # a texture value per channel and the two tilts
    inside = capture.mask[0].bool() & (dof >= 3) & (sse > 0)
    if not bool(inside.any()):
        return Screen(False, "no pixel with enough valid observations to read a tilt from")
    f = (gain / 2) / ((sse - gain).clamp_min(1e-300) / dof)
    p = (1 + 2 * f / dof).pow(-dof / 2)  # the F(2, d) survival function, exact
    share = float((p[inside] < TILT_P).double().mean())
    explained = float((gain / sse.clamp_min(1e-300))[inside].median())
    reading = {"tilt_share": share, "explained_median": explained, "pixels": int(inside.sum())}
    if share <= TILT_SHARE:
        return Screen(False, f"the reference fit's residual follows no tilt beyond noise: {share:.1%} of pixels at p < "
                             f"{TILT_P:g} ({TILT_P:.0%} by chance, {TILT_SHARE:.0%} needed)", reading)
    if explained < min_explained:
        return Screen(False, f"tilts explain {explained:.1%} of the typical pixel's residual in-sample ({share:.1%} of "
                             f"pixels beyond noise), under the {min_explained:.0%} the test needs", reading)
    return Screen(True, f"{share:.1%} of pixels follow a tilt beyond noise (p < {TILT_P:g}; {TILT_P:.0%} by chance), "
                        f"explaining {explained:.1%} of the typical pixel's residual", reading)


def clipping_screen(fit: FitResult, capture: Capture) -> Screen:
    """The clipping's screen (module docstring) of ``fit``, the reference fitted to ``capture`` read per channel."""
    v = valid_pixels(capture)
    sq = (_render(fit, capture) - capture.images.double()).square()
    partial = capture.saturated.any(1, keepdim=True) & v  # the unclipped channels of partly clipped observations
    total = float(sq[v].sum())
    share = float(sq[partial].sum()) / total if total > 0 else 0.0
    reading = {"residual_share": share, "observations": int(partial.any(1).sum())}
    if share >= CLIPPING_SHARE:
        return Screen(True, f"the partly clipped observations' other channels hold {share:.1%} of the residual", reading)
    return Screen(False, f"the partly clipped observations' other channels hold {share:.1%} of the residual only "
                         f"(< {CLIPPING_SHARE:.0%}: the test took 'pixel' on random scenes from 27 % only)", reading)


def light_screen(fit: FitResult, capture: Capture) -> Screen:
    """The flash move's screen (module docstring) of ``fit``, the reference fitted to ``capture``."""
    v = valid_pixels(capture)
    y = capture.images.double()

    def sse(pred: Tensor) -> float:
        return float((pred.double() - y)[v].square().sum())

    def render(lights: Tensor) -> Tensor:
        with torch.no_grad():
            return fit.render(lights.to(capture.lights.dtype), capture.intensities, capture.cameras)

    before = sse(render(capture.lights))
    off = fit_offsets(capture, render, shared=True, iters=LIGHT_ITERS)
    after = sse(render(move_capture(capture, off.to(capture.lights.dtype)).lights))
    share = (before - after) / before if before > 0 else 0.0
    reading = {"in_sample_gain": share, "move": [float(x) for x in off[0].tolist()]}
    if share >= LIGHT_SHARE:
        return Screen(True, f"moving every light lowers the fitted shots' error by {share:.2%}", reading)
    return Screen(False, f"moving every light lowers the fitted shots' error by {share:.2%} only "
                         f"(< {LIGHT_SHARE:.1%}: no left-out gain of the test's size can follow)", reading)
