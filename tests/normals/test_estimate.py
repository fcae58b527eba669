"""Normals from the photos (torchmetal.normals.estimate_normals): accuracy against the generator's truth,
flat when flat, robustness to clipped highlights and glints, bad input, the pipeline/CLI option,
and the material (save/load, ONNX parity) with estimated normals.

Captures come from the zoo's numpy generator (:mod:`torchmetal.synth.zoo_render`), which shares
no code with the fit, and are scored against its noise-free truth.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from torchmetal.errors import InputError
from torchmetal.io.capture import load_capture
from torchmetal.io.shared_data import shared_data_dir
from torchmetal.normals import angular_error, estimate_normals, with_normals
from torchmetal.synth.zoo_render import Scene, make_case

DATA = shared_data_dir()
SPHERE = DATA / "uw_gray_sphere"


def _case(tmp_path, name: str, **kw):
    base = dict(size=40, shots=12, held=2, noise=0.005, encoding="linear16", seed=21)
    base.update(kw)
    case = make_case(Scene(name, **base), tmp_path / name)
    return case, load_capture(case.capture_dir)


def _truth(case) -> torch.Tensor:
    return torch.as_tensor(case.truth.normals, dtype=torch.float32)


def _check_unit(n: torch.Tensor) -> None:
    assert bool(torch.isfinite(n).all())
    assert float((n.norm(dim=0) - 1).abs().max()) < 1e-5
    assert float(n[2].min()) > 0.0


@pytest.fixture(scope="module")
def directional(tmp_path_factory):
    """Bumpy, 16 directional lights (a third near the mirror direction), orthographic camera, sharp highlights."""
    case, cap = _case(tmp_path_factory.mktemp("dir"), "dir", shots=16, layout="directional", camera="ortho",
                      normals="bumpy", s=1.0, alpha=150, exposure=1.2)
    return case, cap, estimate_normals(cap)


@pytest.fixture(scope="module")
def point(tmp_path_factory):
    """Bumpy, point lights over a hemisphere, perspective camera."""
    case, cap = _case(tmp_path_factory.mktemp("pt"), "pt", layout="hemisphere", camera="jitter", normals="bumpy",
                      s=0.5, alpha=60)
    return case, cap, estimate_normals(cap)


class TestAccuracy:
    def test_directional_lights(self, directional):
        case, cap, est = directional
        _check_unit(est.normals)
        err = angular_error(est.normals, _truth(case))
        flat = angular_error(cap.normals * 0 + torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1), _truth(case))
        assert float(err.mean()) < 0.1 and float(err.median()) < 0.06, (float(err.mean()), float(err.median()))
        assert float(err.mean()) < 0.05 * float(flat.mean())
        assert est.report["unsolved_pixels"] == 0

    def test_point_lights(self, point):
        case, cap, est = point
        _check_unit(est.normals)
        err = angular_error(est.normals, _truth(case))
        assert float(err.mean()) < 0.3 and float(err.median()) < 0.25, (float(err.mean()), float(err.median()))

    def test_joint_removes_the_lobe_bias(self, directional):
        # the joint stage brings s, α to the truth's (1.0, 150); alternating alone stops short (lower
        # α and s: the normals' errors broaden the lobe the Phong fit sees) with larger normal errors
        case, cap, est = directional
        assert abs(float(est.s.mean()) - 1.0) < 0.05 and abs(float(est.alpha.mean()) / 150 - 1) < 0.03, (est.s, est.alpha)
        alt = estimate_normals(cap, rounds=2, joint=False)
        assert float(alt.alpha.mean()) < float(est.alpha.mean()) - 3.0
        assert float(angular_error(alt.normals, _truth(case)).mean()) > 2 * float(angular_error(est.normals, _truth(case)).mean())


class TestRestart:
    def test_stuck_patches_get_a_second_chance(self, tmp_path):
        # the zoo's photo_bumpy_noise2 at 96²: dark photo texture, noise 0.02, a ring of point lights.
        # Without the restart, patches near highlights stay in a wrong minimum (20–50° off, the true
        # normal costing a tenth of theirs): mean 2.17°, 740 pixels > 5°; with it 1.31°, 552
        from torchmetal.synth.zoo import SCENES
        from torchmetal.synth.zoo import make_case as zoo_case

        case = zoo_case(SCENES["photo_bumpy_noise2"].with_(size=96), tmp_path / "pbn2")
        cap = load_capture(case.capture_dir)
        est = estimate_normals(cap)
        err = angular_error(est.normals, _truth(case))
        rep = [r for r in est.report["rounds"] if r["round"] == "restart"][0]
        assert rep["restart_kept"] > 0 and rep["moves"] > 0, rep
        assert float(err.mean()) < 1.5 and float(err.median()) < 0.3, (float(err.mean()), float(err.median()))
        off = angular_error(estimate_normals(cap, restart=False).normals, _truth(case))
        assert float(err.mean()) < 0.7 * float(off.mean()) and float((err > 5).sum()) < 0.85 * float((off > 5).sum())


def _sphere(size: int = 56, s: float = 0.1, alpha: float = 10.0, noise: float = 0.004, seed: int = 3):
    """A grey sphere under 12 directional lights 5–40° from the orthographic camera, all from one side
    (azimuths 30–125°, like a hand-held lamp: uw_gray_sphere's kind of layout), with a Phong lobe
    (docs/design.md §2.2), noise and 8-bit quantisation, rendered here in float64."""
    import math

    from torchmetal.io.capture import Capture

    g = torch.Generator().manual_seed(seed)
    c = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2 - 1
    y, x = -c.view(-1, 1).expand(size, size), c.view(1, -1).expand(size, size)
    rho2 = x * x + y * y
    mask = rho2 < 0.97 ** 2
    n = torch.stack([x, y, (1 - rho2).clamp_min(0).sqrt()])
    n = torch.where(mask, n, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).view(3, 1, 1))
    el = torch.tensor([40, 10, 10, 25, 35, 35, 30, 25, 20, 20, 5, 25], dtype=torch.float64) * (math.pi / 180)
    az = torch.tensor([50, 60, 110, 105, 125, 100, 60, 80, 70, 85, 30, 115], dtype=torch.float64) * (math.pi / 180)
    l = torch.stack([el.sin() * az.cos(), el.sin() * az.sin(), el.cos()], 1)
    nl = torch.einsum("kc,chw->khw", l, n)
    rv = (2 * nl * n[2] - l[:, 2].view(-1, 1, 1)).clamp_min(0)  # r·v, v = z
    d = torch.tensor([0.75, 0.73, 0.7], dtype=torch.float64).view(1, 3, 1, 1)
    img = d * nl.clamp_min(0).unsqueeze(1) + (s * (nl > 0) * rv.pow(alpha)).unsqueeze(1)
    img = (img + noise * torch.randn(img.shape, generator=g, dtype=img.dtype)).clamp(0, 1).mul(255).round().div(255)
    return Capture(images=img.float(), normals=n.float(), mask=mask.view(1, size, size),
                   lights=torch.cat([l, torch.zeros(12, 1, dtype=torch.float64)], 1).float(), intensities=torch.ones(12, 3),
                   cameras=torch.tensor([[0.0, 0.0, 1.0, 0.0]]).expand(12, 4).clone(), size=(2.0, 2.0))


class TestWeakLobe:
    def test_weak_broad_lobe_is_found(self):
        # s = 0.1 (≈ 14 % of the diffuse), α = 10: Lambertian normals tilted towards the half vectors
        # absorb the lobe and the Phong fits then see no highlight (s = 0, 1.4° mean, 2–4° in the
        # centre); the weak-lobe try fits it jointly with the normals (0.38° here)
        cap = _sphere()
        est = estimate_normals(cap)
        err = angular_error(est.normals, cap.normals, cap.mask[0])
        assert float(err.mean()) < 0.6 and float(err.median()) < 0.45, (float(err.mean()), float(err.median()))
        assert abs(float(est.s.mean()) / 0.1 - 1) < 0.15 and abs(float(est.alpha.mean()) / 10 - 1) < 0.15, (est.s, est.alpha)
        off = estimate_normals(cap, weak_lobe=False)
        if not bool((off.s > 0).any()):  # the trap the try gets out of
            assert float(angular_error(off.normals, cap.normals, cap.mask[0]).mean()) > 2 * float(err.mean())

    def test_lambertian_sphere_gets_no_lobe(self):
        cap = _sphere(s=0.0)
        est = estimate_normals(cap)
        tried = [r for r in est.report["rounds"] if r["round"] == "weak_lobe"]
        assert float(est.s.abs().max()) == 0.0 and all(not r["kept"] for r in tried), (est.s, tried)
        err = angular_error(est.normals, cap.normals, cap.mask[0])
        assert float(err.mean()) < 0.5, float(err.mean())


    def test_two_materials_not_worse(self, tmp_path):
        # a flat sample with a sharper second material the global lobe cannot fit: the estimate tilts the
        # disc's normals to explain its highlights (3° mean). Small cost gains there buy more tilt, so the
        # restart's moves need a real gain (MOVE_GAIN): 2.9625° without the step, 2.9636° with it
        # (3.13° when any gain was taken)
        from torchmetal.synth.zoo import SCENES
        from torchmetal.synth.zoo import make_case as zoo_case

        case = zoo_case(SCENES["two_materials"].with_(size=128), tmp_path / "two")
        cap = load_capture(case.capture_dir)
        on = angular_error(estimate_normals(cap).normals, _truth(case))
        off = angular_error(estimate_normals(cap, restart=False).normals, _truth(case))
        assert float(on.mean()) < float(off.mean()) + 0.02, (float(on.mean()), float(off.mean()))


class TestFlat:
    def test_flat_sample_stays_flat(self, tmp_path):
        case, cap = _case(tmp_path, "flat", layout="hemisphere", camera="jitter", s=0.5, alpha=60)
        est = estimate_normals(cap)
        _check_unit(est.normals)
        tilt = angular_error(est.normals, _truth(case))
        assert float(tilt.mean()) < 0.05 and est.report["kept_flat"] > 0.9 * est.report["pixels"], (float(tilt.mean()), est.report)
        noisy = angular_error(estimate_normals(cap, flat_test=False).normals, _truth(case))
        assert 0.05 < float(noisy.mean()) < 0.4  # without the test: the flat normal plus noise

    def test_masked_pixels_keep_flat(self, directional):
        _, cap, _ = directional
        mask = cap.mask.clone()
        mask[:, :, :10] = False
        est = estimate_normals(replace(cap, mask=mask), rounds=0)
        out = est.normals[:, ~mask[0]]
        assert bool((out[2] == 1).all() and (out[:2] == 0).all())


class TestRobust:
    def test_saturated_highlights(self, tmp_path):
        # strong, clipped highlights (8-bit): the clipped shots are left out, not taken for shading
        case, cap = _case(tmp_path, "sat", shots=16, layout="directional", camera="ortho", normals="bumpy", s=3.0,
                          alpha=80, exposure=2.0, encoding="srgb8")
        clipped = float(cap.saturated.any(1).float().mean())
        assert clipped > 0.1  # a tenth of the observations clip
        est = estimate_normals(cap)
        err = angular_error(est.normals, _truth(case))
        assert float(err.mean()) < 0.2 and float(err.median()) < 0.12, (float(err.mean()), float(err.median()))

    def test_glints_are_not_shading(self, directional):
        # bright 1-px glints on 2 % of the pixels of every shot (unflagged): the robust weights drop them
        case, cap, clean = directional
        g = torch.Generator().manual_seed(5)
        hit = torch.rand(cap.images.shape[0], 1, *cap.images.shape[2:], generator=g) < 0.02
        images = torch.where(hit, cap.images + 0.8, cap.images)
        est = estimate_normals(replace(cap, images=images))
        err = angular_error(est.normals, _truth(case))
        base = angular_error(clean.normals, _truth(case))
        assert float(err.median()) < float(base.median()) + 0.1, (float(err.median()), float(base.median()))
        assert float(err.mean()) < 0.3, float(err.mean())


class TestBadInput:
    def test_too_few_shots(self, directional):
        _, cap, _ = directional
        with pytest.raises(InputError, match="at least 3 shots"):
            estimate_normals(cap.subset([0, 1]))

    def test_coplanar_lights(self, directional):
        _, cap, _ = directional
        one = cap.lights[:1].expand(cap.num_shots, 4).clone()
        with pytest.raises(InputError, match="non-coplanar"):
            estimate_normals(replace(cap, lights=one))

    def test_bad_mode_and_arguments(self, directional):
        _, cap, _ = directional
        with pytest.raises(InputError, match="normals: expected one of"):
            with_normals(cap, "guess")
        with pytest.raises(InputError, match="rounds"):
            estimate_normals(cap, rounds=-1)
        from torchmetal.pipeline import fit_material

        with pytest.raises(InputError, match="normals: expected one of"):
            fit_material(cap, normals="guess")


class TestModes:
    def test_given_and_flat(self, directional):
        case, cap, _ = directional
        given, rep = with_normals(cap, "given")
        assert given is cap and rep["mode"] == "given"
        flat, rep = with_normals(cap, "flat")
        assert flat.flat and rep["mode"] == "flat"


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A bumpy capture fitted with normals="estimate", and its material saved and loaded back."""
    from torchmetal.material import load_material, save_material
    from torchmetal.pipeline import fit_material

    tmp = tmp_path_factory.mktemp("mat")
    case, cap = _case(tmp, "mat", size=32, shots=10, layout="directional", camera="ortho", normals="bumpy", s=1.0,
                      alpha=100)
    res = fit_material(cap, normals="estimate", flakes="off")
    out = save_material(res.material, tmp / "material")
    return case, cap, res, out, load_material(out)


class TestMaterial:
    def test_pipeline_save_load_render(self, fitted):
        from torchmetal.pipeline import fit_material
        from torchmetal.renderer import MaterialRenderer

        case, cap, res, out, back = fitted
        m = res.material
        assert m.normals is not None and res.report["normals"]["mode"] == "estimate"
        assert torch.equal(m.normals, res.fit.normals.float())  # the material keeps the normals it was fitted with
        assert (out / "normals.npy").is_file() and torch.equal(back.normals, m.normals)
        r = MaterialRenderer(back).eval()
        assert not r.flat
        # the estimated normals reproduce held-out shots far better than flat ones do
        f32 = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float32))  # noqa: E731
        ref = torch.as_tensor(case.clean).clamp(0, 1)
        flat = fit_material(cap, normals="flat", flakes="off").material
        assert flat.normals is None
        with torch.no_grad():
            args = (f32(case.held_lights), f32(case.held_intensities), f32(case.held_cameras))
            e_est = float((r(*args).clamp(0, 1) - ref).pow(2).mean())
            e_flat = float((MaterialRenderer(flat)(*args).clamp(0, 1) - ref).pow(2).mean())
        assert e_est < 0.1 * e_flat, (e_est, e_flat)

    @pytest.mark.slow
    def test_onnx_parity(self, fitted, tmp_path):
        from torchmetal.onnx_export import export_onnx, verify_onnx
        from torchmetal.renderer import MaterialRenderer

        r = MaterialRenderer(fitted[4]).eval()
        path = export_onnx(r, tmp_path / "renderer.onnx", check=False)
        assert verify_onnx(path, r) <= 1e-4

    def test_cli(self, tmp_path):
        from torchmetal.cli import main

        case, _ = _case(tmp_path, "cli", size=24, shots=8, layout="directional", camera="ortho", normals="bumpy",
                        s=1.0, alpha=100)
        assert main(["fit", str(case.capture_dir), "-o", str(tmp_path / "est"), "--normals", "estimate", "-q",
                     "--flakes", "off"]) == 0
        n = np.load(tmp_path / "est" / "normals.npy")
        assert n.shape == (24, 24, 3) and np.isfinite(n).all() and (n[..., 2] > 0).all()
        assert main(["fit", str(case.capture_dir), "-o", str(tmp_path / "flat"), "--normals", "flat", "-q",
                     "--flakes", "off"]) == 0
        assert not (tmp_path / "flat" / "normals.npy").exists()


def _sphere_half():
    # directional lights and an orthographic camera: the geometry does not depend on the pixel
    # position, so every other pixel is an exact smaller capture
    cap = load_capture(SPHERE)
    return replace(cap, images=cap.images[..., ::2, ::2], normals=cap.normals[:, ::2, ::2], mask=cap.mask[:, ::2, ::2],
                   saturated=cap.saturated[..., ::2, ::2])


@pytest.mark.skipif(not SPHERE.is_dir(), reason="shared/data/uw_gray_sphere is absent (real data, not in CI)")
def test_uw_gray_sphere():
    sub = _sphere_half()
    est = estimate_normals(sub, rounds=1)
    err = angular_error(est.normals, sub.normals, sub.mask[0])
    # 4.85° mean, 3.98° median here (full size 4.78°, 4.00°); Lambertian least squares 5.5°. The data
    # limit it: the estimate explains the photos better than the analytic normals do on 99.7 % of the
    # pixels; with each light's direction and intensity re-fitted to the true normals it is still
    # 3.9° (the given directions are 1–7° off those); the lit rim (r > 0.95 R) is 13–15° off on the
    # photos, 0.3° on the twin below
    assert float(err.mean()) < 5.0 and float(err.median()) < 4.1, (float(err.mean()), float(err.median()))


@pytest.mark.skipif(not SPHERE.is_dir(), reason="shared/data/uw_gray_sphere is absent (real data, not in CI)")
def test_uw_gray_sphere_twin():
    # the photos re-rendered from the capture's own normals and lights (Lambertian, 8-bit, noise 1/255):
    # on data that fits the model the estimator is well under 1° on this geometry, so the 4.8° on
    # the photos is the data's (light calibration, non-Lambertian shading, the rim), not the estimator's
    sub = _sphere_half()
    g = torch.Generator().manual_seed(0)
    nl = torch.einsum("kc,chw->khw", sub.lights[:, :3], sub.normals).clamp_min(0).unsqueeze(1)
    img = torch.tensor([0.75, 0.73, 0.7]).view(1, 3, 1, 1) * nl + torch.randn(nl.shape[0], 3, *nl.shape[2:], generator=g) / 255
    img = torch.where(sub.mask.unsqueeze(0), img, torch.zeros_like(img)).clamp(0, 1).mul(255).round().div(255)
    twin = replace(sub, images=img, saturated=img >= 1.0)
    est = estimate_normals(twin, rounds=1)
    err = angular_error(est.normals, twin.normals, twin.mask[0])
    assert float(err.mean()) < 1.0 and float(err.median()) < 0.45, (float(err.mean()), float(err.median()))
