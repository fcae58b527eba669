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

On flake scenes, ``psnr`` has its own yardstick: ``oracle_sparkles``, the truth with its flakes drawn
again from the same statistics (its mean squared error over :data:`SPARKLE_DRAWS` draws). Sparkles at random places
lose PSNR against any render without them, the truth's own statistics included (zoo flakes_bright_hemi:
39.98 dB redrawn against 42.89 flake-free), so a model's sparkles are judged against that oracle and
its left-out sparkle count against the truth's (``sparkle_ratio``), never against a render without
flakes.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from torchmetal.bench.scoring import glint_scores, rel_err

SPARKLE_DRAWS = 3  # redraws of the true flakes: one draw's PSNR varies by ~1 dB (zoo flakes_half 42.4-45.3)

if TYPE_CHECKING:  # annotations only: a real import would load torch (this module imports numpy only)
    from torchmetal.material import Material
    from torchmetal.pipeline import PipelineResult

#: "paper": the seed paper's scheme on the capture as the paper has it: its lights and its normals (normals.npy, else
#: flat), a clipped channel dropped alone, no flakes (docs/measurements.md: "auto" normals scored the same, at 4× the time)
METHODS = {
    "default": {},
    "paper": {"scheme": "paper", "flakes": "off", "light": "off", "clipping": "channel", "normals": "given"},
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


def score_fit(case, result: PipelineResult, seconds: float, truth_base: np.ndarray | None = None) -> dict:
    """One method's numbers on one case; ``truth_base`` (H, 3, n, n): the held-out truth without flakes, for
    the sparkle count ratio on flake scenes."""
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
        if "color" in ts:  # the flakes' mean colour (channel mean) over the drawn flakes'
            row["color_ratio"] = float(np.mean(fm.color_mean)) / ts["color"]
    if truth_base is not None:
        g = _glints(case, truth_base, pred, coat)
        row["sparkle_ratio"], row["truth_sparkles"] = float(g["count_ratio"]), int(g["truth_sparkles"])
    return row


def _glints(case, truth_base: np.ndarray, pred: np.ndarray, pred_base: np.ndarray) -> dict:
    """Left-out sparkle counts of truth and prediction (bench.scoring.glint_scores)."""
    return glint_scores(case.clean, truth_base, pred, pred_base)


def _sparkle_oracle(case, truth_base: np.ndarray) -> dict:
    """PSNR (of the mean squared error) and sparkle count ratio (mean) of the truth with its flakes redrawn, over
    SPARKLE_DRAWS draws."""
    from torchmetal.synth.zoo_render import redrawn_flakes_render

    renders = [redrawn_flakes_render(case, k) for k in range(SPARKLE_DRAWS)]
    # the draws' mean squared error as a PSNR (peak 1): a mean of PSNRs would let a draw without a glint in the
    # held-out shots (∞ dB in the limit) outweigh the others
    mse = np.mean([10.0 ** (-_psnr(r, case.clean) / 10.0) for r in renders])
    return {"oracle_sparkles": float(-10.0 * np.log10(mse)),
            "oracle_sparkle_ratio": float(np.mean([_glints(case, truth_base, r, truth_base)["count_ratio"]
                                                    for r in renders]))}


def run_scene(scene, methods: dict | None = None, *, workdir: str | Path | None = None) -> dict:
    """Write, fit and score one scene; returns {"scene", "oracle", method name: row}."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.capture import load_capture
    from torchmetal.pipeline import fit_material
    from torchmetal.synth.zoo import make_case, oracle_render
    from torchmetal.synth.zoo_render import held_out_renders

    methods = METHODS if methods is None else methods
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        case = make_case(scene, Path(tmp) / scene.name)
        out = {"scene": scene.name, "oracle": _psnr(oracle_render(case), case.clean), "truth": case.truth_stats}
        base = None
        if scene.flakes is not None:
            base = held_out_renders(case, flakes=False)
            out.update(_sparkle_oracle(case, base))
        for name, kw in methods.items():
            t0 = time.perf_counter()
            capture = load_capture(case.capture_dir)
            res = fit_material(capture, **kw)
            out[name] = score_fit(case, res, time.perf_counter() - t0, base)
    return out
