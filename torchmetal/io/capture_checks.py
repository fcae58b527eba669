"""The capture's value checks (docs/design.md §2.1): each problem is a one-line error naming what was
expected and what was found. Used by :mod:`torchmetal.io.capture` and by everything that takes lights,
cameras or pixels from a user (the CLI, the viewer's server, the tiled fit)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from torchmetal.errors import CaptureError, InputError, TorchmetalError

F32_MAX = float(np.finfo(np.float32).max)
REFLECTANCE_MAX = 1e12  # pixel / irradiance above this is not a surface (and overflows float32 when squared)


def short_repr(x: object, limit: int = 60) -> str:
    r = repr(x)
    return r if len(r) <= limit else r[: limit - 3] + "..."


def _float(v: int | float) -> float:
    """float(v), with ±inf for an integer beyond the float range (a JSON literal of 309+ digits)."""
    try:
        return float(v)
    except OverflowError:
        return math.inf if v > 0 else -math.inf


def numbers(values: object, n: int, label: str, error: type[TorchmetalError] = CaptureError) -> list[float]:
    """A JSON/list value that must be ``n`` finite numbers."""
    ok = isinstance(values, (list, tuple)) and len(values) == n
    ok = ok and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)  # type: ignore[union-attr]
    if not ok:
        found = f"{len(values)} values {short_repr(values)}" if isinstance(values, (list, tuple)) else short_repr(values)
        raise error(f"{label}: expected {n} numbers, found {found}")
    out = [_float(v) for v in values]  # type: ignore[union-attr]
    if not all(math.isfinite(v) for v in out):
        raise error(f"{label}: expected finite numbers, found {short_repr(out)}")
    if any(abs(v) > F32_MAX for v in out):  # stored and computed in float32: inf there
        raise error(f"{label}: expected numbers within the float32 range (|v| <= {F32_MAX:.4g}), found {short_repr(out)}")
    return out


def check_light(v: list[float], label: str, error: type[TorchmetalError] = CaptureError) -> None:
    x, y, z, w = v
    if w not in (0.0, 1.0):
        raise error(f"{label}: expected w = 1 (point light) or w = 0 (directional), found w = {w:g}")
    if z <= 0:
        where = "a point light above the surface plane z = 0" if w == 1 else "a direction above the horizon"
        raise error(f"{label}: expected z > 0 ({where}), found z = {z:g}")


def check_camera(v: list[float], label: str, error: type[TorchmetalError] = CaptureError) -> None:
    x, y, z, w = v
    if w not in (0.0, 1.0):
        raise error(f"{label}: expected w = 1 (camera position) or w = 0 (orthographic direction), found w = {w:g}")
    if z <= 0:
        raise error(f"{label}: expected z > 0 (camera above the surface), found z = {z:g}")


def check_intensity(v: list[float], label: str, error: type[TorchmetalError] = CaptureError) -> None:
    if min(v) < 0:
        raise error(f"{label}: expected values >= 0, found {short_repr(v)}")


def check_light_camera(
    light: Tensor, intensity: Tensor, camera: Tensor, *, labels: Sequence[str] | None = None,
    error: type[TorchmetalError] = InputError,
) -> None:
    """Check B shots' lights (B, 4), intensities (B, 3) and cameras (B, 4) like a capture's.

    Homogeneous w must be exactly 0 or 1, everything finite, z > 0 (lights above the surface
    plane / horizon, cameras above the surface) and intensities >= 0. Raises ``error`` (one
    line, naming the shot) — :class:`InputError` by default, for render inputs.
    """
    for name, t, width in (("light", light, 4), ("light_intensity", intensity, 3), ("camera", camera, 4)):
        if not isinstance(t, Tensor) or t.dim() != 2 or t.shape[1] != width:
            found = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise error(f"{name}: expected shape (B, {width}), found {found}")
        if not t.is_floating_point():
            raise error(f"{name}: expected a floating-point tensor, found dtype {t.dtype}")
    if not (light.shape[0] == intensity.shape[0] == camera.shape[0]):
        raise error(f"light/light_intensity/camera: expected the same batch size B, found "
                    f"{light.shape[0]}, {intensity.shape[0]}, {camera.shape[0]}")
    rows = (t.detach().cpu().double().tolist() for t in (light, intensity, camera))
    for k, (lv, iv, cv) in enumerate(zip(*rows)):
        label = labels[k] if labels is not None else f"shot {k}"
        check_light(numbers(lv, 4, f"{label}: light", error), f"{label}: light", error)
        check_intensity(numbers(iv, 3, f"{label}: light_intensity", error), f"{label}: light_intensity", error)
        check_camera(numbers(cv, 4, f"{label}: camera", error), f"{label}: camera", error)


def check_size(size: object, label: str) -> tuple[float, float]:
    ok = isinstance(size, (tuple, list)) and len(size) == 2
    ok = ok and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(_float(v)) and v > 0 for v in size)  # type: ignore[union-attr]
    if not ok:
        raise CaptureError(f"{label}: expected positive finite (width, height), found {short_repr(size)}")
    return float(size[0]), float(size[1])  # type: ignore[index]


def check_pixels(t: Tensor, label: str) -> float:
    """Finite and >= 0, in one pass (NaN propagates to min/max); details only on failure.
    Returns the largest value (0 for an empty tensor)."""
    if t.numel() == 0:
        return 0.0
    lo, hi = torch.aminmax(t)
    lo, hi = float(lo), float(hi)
    if math.isfinite(lo) and math.isfinite(hi) and lo >= 0:
        return hi
    bad = ~torch.isfinite(t)
    if bool(bad.any()):
        n = int(bad.sum())
        kind = "NaN" if bool(torch.isnan(t).any()) else "Inf"
        raise CaptureError(f"{label}: expected finite pixel values, found {n} non-finite ({kind})")
    raise CaptureError(f"{label}: expected pixel values >= 0, found minimum {lo:.4g}")


def check_exposure(peaks: Sequence[float], lights: Tensor, intensities: Tensor, size: tuple[float, float],
                    labels: Sequence[str]) -> None:
    """Each shot's brightest pixel against the least irradiance its light gives the surface.

    A pixel is irradiance × reflectance; a ratio above :data:`REFLECTANCE_MAX` is no surface but a
    light position or intensity off by orders of magnitude (and it overflows float32 once squared
    in a fit). E = intensity / d² (d to the farthest surface corner) for a point light, intensity
    for a directional one. Dark shots (zero intensity or all-black images) are not checked.
    """
    hw, hh = size[0] / 2, size[1] / 2
    corners = torch.tensor([[hw, hh, 0.0], [-hw, hh, 0.0], [hw, -hh, 0.0], [-hw, -hh, 0.0]], dtype=torch.float64)
    lights, intensities = lights.detach().cpu().double(), intensities.detach().cpu().double()
    for k, peak in enumerate(peaks):
        top = float(intensities[k].max())
        if peak <= 0 or top <= 0:
            continue
        if float(lights[k, 3]) == 1.0:
            d2 = float(((corners - lights[k, :3]) ** 2).sum(1).max())
            irradiance = top / d2
        else:
            irradiance = top
        ratio = peak / irradiance if irradiance > 0 else math.inf
        if ratio > REFLECTANCE_MAX:
            raise CaptureError(
                f"{labels[k]}: expected image values at most {REFLECTANCE_MAX:.0e} x the irradiance on the surface "
                f"(light_intensity / distance²), found {ratio:.3g} x (brightest pixel {peak:.4g}, irradiance "
                f"{irradiance:.4g}): the light is too far or too weak for its photo"
            )


def shape_error(name: str, want: str, x: object) -> CaptureError:
    found = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
    return CaptureError(f"Capture.{name}: expected shape {want}, found {found}")
