"""Evidence for the flake-density map (:mod:`torchmetal.flakes.estimate.density_map`): where the sparkles are.

Two samples, each fitted by :func:`~torchmetal.pipeline.fit_material` without one shot, which is then
rendered with the uniform flake model and with the density map (whichever the fit kept):

- zoo ``flakes_half`` (glitter on the left half only): the held-out shots' clean truth (with a fixed
  noise σ = ``NOISE`` added to truth and renders alike, so the sparkle threshold is a photo's) against
  the renders; sparkles counted inside (left half) and outside (right half) the glitter;
- the real card ``cards_blue`` (when the shared data is present; never copied into the repository):
  shot ``CARD_HOLD`` left out; "inside" are the blocks the map keeps at ≥ half the global density,
  "outside" the others.

Sparkles are :func:`~torchmetal.flakes.density_choice.sparkle_counts` (MD's local maxima above 5
robust σ). Writes ``<name>.png`` (left to right: photo, uniform render, map render; sRGB, common
exposure) and ``sparkle_map.json`` to the output directory.

    python -m torchmetal.bench.sparkle_map OUT_DIR [--card PATH] [--no-card]
"""

from __future__ import annotations

import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from torchmetal.flakes.choice import shot_valid
from torchmetal.flakes.density_choice import sparkle_counts
from torchmetal.io.capture import load_capture
from torchmetal.io.shared_data import shared_data_dir
from torchmetal.pipeline import fit_material
from torchmetal.renderer import MaterialRenderer
from torchmetal.synth.zoo import SCENES, make_case

NOISE = 0.005
CARD_HOLD = 3
CARD = shared_data_dir() / "cards_blue"  # $TORCHMETAL_SHARED_DATA, default ../shared/data beside the checkout


def _png(path: Path, images: list[np.ndarray]) -> None:
    """(3, H, W) linear images side by side, one exposure (the first's 99.5th percentile), sRGB 8-bit."""
    import cv2

    scale = 1.0 / max(float(np.percentile(images[0], 99.5)), 1e-6)
    row = np.concatenate([np.clip(im * scale, 0, 1) for im in images], axis=2).transpose(1, 2, 0)
    srgb = np.where(row <= 0.0031308, 12.92 * row, 1.055 * np.power(row, 1 / 2.4) - 0.055)
    cv2.imwrite(str(path), np.ascontiguousarray((srgb * 255 + 0.5).astype(np.uint8)[..., ::-1]))


def _render(material, light, intensity, camera) -> torch.Tensor:
    with torch.no_grad():
        return MaterialRenderer(material)(light.float().view(1, 4), intensity.float().view(1, 3), camera.float().view(1, 4))[0]


def _split(counts: torch.Tensor, inside: torch.Tensor) -> dict:
    return {"inside": float(counts[inside].sum()), "outside": float(counts[~inside].sum())}


def _candidates(material) -> dict:
    m = material.flakes
    uniform = replace(material, flakes=replace(m, density_map=None, color_map=None, area_map=None)) if m is not None else material
    return {"uniform": uniform, "map": material}


def half_scene(out: Path, *, size: int = 256) -> dict:
    """Fit zoo flakes_half and score its held-out shots inside/outside the glitter (left/right half)."""
    with tempfile.TemporaryDirectory() as tmp:
        case = make_case(SCENES["flakes_half"].with_(size=size), Path(tmp) / "half")
        res = fit_material(load_capture(case.capture_dir), seed=0)
    mat = res.material
    rep = {"decision": (res.flakes.report.get("density_map_choice") if res.flakes else None),
           "flakes": mat.flakes is not None}
    if mat.flakes is not None and mat.flakes.density_map is not None:
        dm = mat.flakes.density_map
        half = dm.shape[1] // 2
        rep["map_left_mean"], rep["map_right_mean"] = float(dm[:, :half].mean()), float(dm[:, dm.shape[1] - half:].mean())
        rep["density_map"] = dm.tolist()
    inside = torch.tensor([[True, False]])
    rng = np.random.default_rng(0)
    per = {c: {"inside": 0.0, "outside": 0.0} for c in ("truth", "uniform", "map")}
    for s in range(len(case.held_lights)):
        light, inten, cam = (torch.from_numpy(np.asarray(a[s])) for a in (case.held_lights, case.held_intensities,
                                                                         case.held_cameras))
        truth = torch.from_numpy(case.clean[s] + NOISE * rng.standard_normal(case.clean[s].shape).astype(np.float32))
        renders = {c: _render(m, light, inten, cam) for c, m in _candidates(mat).items()}
        for c, img in renders.items():
            noisy = img + torch.from_numpy(NOISE * rng.standard_normal(tuple(img.shape)).astype(np.float32))
            p, o = sparkle_counts(noisy, truth, (1, 2))
            for key, v in _split(p, inside).items():
                per[c][key] += v
            if c == "uniform":
                for key, v in _split(o, inside).items():
                    per["truth"][key] += v
        if s == 0:
            _png(out / "flakes_half.png", [truth.numpy(), renders["uniform"].numpy(), renders["map"].numpy()])
    rep["sparkles"] = per
    return rep


def card(out: Path, path: Path = CARD) -> dict:
    """Fit cards_blue without shot CARD_HOLD and score that shot inside/outside the map's glitter."""
    cap = load_capture(path)
    fit_cap = cap.subset([k for k in range(cap.num_shots) if k != CARD_HOLD])
    one = cap.subset([CARD_HOLD])
    res = fit_material(fit_cap, seed=0)
    mat = res.material
    rep = {"decision": res.flakes.report.get("density_map_choice") if res.flakes else None, "flakes": mat.flakes is not None}
    if mat.flakes is None:
        return rep
    dm = mat.flakes.density_map
    grid = tuple(dm.shape) if dm is not None else (8, 8)
    inside = dm >= 0.5 if dm is not None else torch.ones(grid, dtype=torch.bool)
    rep["glitter_blocks"] = [int(inside.sum()), int(inside.numel())]
    photo = one.images[0].float()
    renders = {c: _render(m, one.lights[0], one.intensities[0], one.cameras[0]) for c, m in _candidates(mat).items()}
    per = {}
    for c, img in renders.items():
        p, o = sparkle_counts(img, photo, grid, shot_valid(one, 0))
        per[c] = _split(p, inside)
        per["photo"] = _split(o, inside)
    rep["sparkles"] = per
    _png(out / "cards_blue.png", [photo.numpy(), renders["uniform"].numpy(), renders["map"].numpy()])
    return rep


def run(out_dir: str | Path, *, card_path: Path | None = CARD, size: int = 256) -> dict:
    """Both benches; writes the PNGs and sparkle_map.json into ``out_dir``; returns the dict."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = {"flakes_half": half_scene(out, size=size)}
    if card_path is not None and (Path(card_path) / "capture.json").is_file():
        result["cards_blue"] = card(out, Path(card_path))
    (out / "sparkle_map.json").write_text(json.dumps(result, indent=1, default=float))
    return result


if __name__ == "__main__":
    args = sys.argv[1:]
    if not args:
        raise SystemExit("usage: python -m torchmetal.bench.sparkle_map OUT_DIR [--card PATH] [--no-card]")
    path = None if "--no-card" in args else (Path(args[args.index("--card") + 1]) if "--card" in args else CARD)
    r = run(args[0], card_path=path)
    for name, v in r.items():
        d = v.get("decision") or {}
        print(name, "winner", d.get("winner"), "scores", d.get("scores"), "sparkles", v.get("sparkles"))
