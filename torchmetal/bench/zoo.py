"""Score fits on the scene zoo (:mod:`torchmetal.synth.zoo`) against the noise-free truth.

For each scene: the capture is written as a user would bring it, fitted from disk with each
method (``fit_material`` options), the material rendered for the held-out shots and compared
with their clean renders (PSNR on linear values clipped to [0, 1], peak 1): ``psnr`` as the
material renders (sparkles included), ``psnr_coat`` the coating alone: rendered without sparkles
and, on flake scenes, scored away from the true flakes (1 px margin) — the statistical field places
flakes at random, not where the held-out photo has them, so there the coating is what a PSNR can
score, and the flake statistics are scored against the truth's. Beside it: the
oracle (true specular and flakes, texture solved from the same shots), s and α errors, whether
a flake model came out and its statistics against the truth, and per-stage times.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from torchmetal.bench.scoring import rel_err

if TYPE_CHECKING:  # annotations only: a real import would load torch (this module imports numpy only)
    from torchmetal.material import Material
    from torchmetal.pipeline import PipelineResult

METHODS = {
    "default": {},
    "paper": {"scheme": "paper", "flakes": "off", "light": "off", "clipping": "channel"},
}


def _psnr(pred: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    # on use: loads torch (this module imports numpy only)
    from torchmetal.metrics import psnr

    return psnr(pred, ref, mask=None if mask is None else mask[None, None])


def render_material(material: Material, lights: np.ndarray, intensities: np.ndarray, cameras: np.ndarray, *,
                    flakes: bool = True) -> np.ndarray:
    """(H, 3, n, n) float32 renders of a material for held-out shots (the torch renderer)."""
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.renderer import MaterialRenderer

    r = MaterialRenderer(material, flakes=flakes)
    f32 = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32))  # noqa: E731
    with torch.no_grad():
        return r(f32(lights), f32(intensities), f32(cameras)).numpy()


def score_fit(case, result: PipelineResult, seconds: float) -> dict:
    """One method's numbers on one case."""
    m = result.material
    pred = render_material(m, case.held_lights, case.held_intensities, case.held_cameras)
    s = float(np.mean(np.asarray(m.s, dtype=np.float64)))
    alpha = float(np.exp(np.mean(np.log(np.asarray(m.alpha, dtype=np.float64)))))
    coat = pred if m.flakes is None else render_material(m, case.held_lights, case.held_intensities,
                                                         case.held_cameras, flakes=False)
    away = None if case.truth.flakes is None else ~case.flake_pixels
    row = {"psnr": _psnr(pred, case.clean), "psnr_coat": _psnr(coat, case.clean, away), "s": s, "alpha": alpha, "time": seconds,
           "stage_times": dict(result.report.get("stage_times", {})), "skipped": list(result.report.get("skipped", [])),
           "flake_model": m.flakes is not None, "specular": getattr(result.fit, "specular", None),
           "lobe": m.lobe}
    if case.scene.phong_truth or case.scene.flakes is not None:
        row["s_err"] = rel_err(s, case.truth_stats["s"])
        row["alpha_err"] = rel_err(alpha, case.truth_stats["alpha"])
    if m.flakes is not None and "density" in case.truth_stats:
        fm, ts = m.flakes, case.truth_stats
        row["density_err"] = rel_err(fm.density, ts["density"])
        row["area_err"] = rel_err(fm.median_area, ts["median_area"])
        row["tilt_err"] = rel_err(fm.tilt_sigma, ts["tilt_sigma"])
    return row


def run_scene(scene, methods: dict | None = None, *, workdir: str | Path | None = None) -> dict:
    """Write, fit and score one scene; returns {"scene", "oracle", method name: row}."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.capture import load_capture
    from torchmetal.pipeline import fit_material
    from torchmetal.synth.zoo import make_case, oracle_render

    methods = METHODS if methods is None else methods
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        case = make_case(scene, Path(tmp) / scene.name)
        out = {"scene": scene.name, "oracle": _psnr(oracle_render(case), case.clean), "truth": case.truth_stats}
        for name, kw in methods.items():
            t0 = time.perf_counter()
            capture = load_capture(case.capture_dir)
            res = fit_material(capture, **kw)
            out[name] = score_fit(case, res, time.perf_counter() - t0)
    return out
