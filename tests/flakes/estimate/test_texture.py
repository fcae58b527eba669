"""texture_without_glints: the texture under detected flakes, re-solved without their glints."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from tests.flakes.scenes import make_scene
from torchmetal.errors import InputError
from torchmetal.flakes.estimate.detect import detect_flakes
from torchmetal.flakes.estimate.texture import texture_without_glints
from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.stage import irradiance_maps
from torchmetal.io.capture import Capture
from torchmetal.phong import phong_render


def _capture(sc) -> Capture:
    return Capture(images=sc.photos, normals=sc.normals, lights=sc.lights, intensities=sc.intensities,
                   cameras=sc.cameras, size=sc.size)


def _least_squares_texture(sc) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel LS texture given the true specular (glints averaged in), and its renders."""
    args = (sc.normals, sc.lights, sc.intensities, sc.cameras, sc.size)
    spec = phong_render(torch.zeros_like(sc.texture), sc.s, sc.alpha, *args)
    gain = phong_render(torch.ones_like(sc.texture), torch.zeros(3), sc.alpha, *args)
    tex = ((gain * (sc.photos - spec)).sum(0) / (gain * gain).sum(0)).clamp_min(0)
    return tex, spec + tex * gain


def _detect(cap: Capture, phong: torch.Tensor):
    return detect_flakes(cap.images, phong, irradiance_maps(cap))


@pytest.fixture(scope="module")
def flaky():
    model = FlakeModel(density=0.006, area_log_mean=math.log(6.0), area_log_std=0.3, color_mean=(0.8, 0.7, 0.5), seed=3)
    sc = make_scene(128, 128, model, shots=8, seed=3)
    return sc, _capture(sc)


class TestTextureWithoutGlints:
    def test_glints_leave_the_texture(self, flaky):
        sc, cap = flaky
        tex, phong = _least_squares_texture(sc)
        det = _detect(cap, phong)
        new, new_phong, changed = texture_without_glints(cap, tex, phong, det.labels)
        flake = sc.sparkle.mean(0).amax(0) > 0.02  # pixels whose glints the LS texture could absorb
        before = (tex - sc.texture)[:, flake].mean()
        after = (new - sc.texture)[:, flake].mean()
        assert float(before) > 0.005  # the LS texture absorbed the glints
        assert abs(float(after)) < 0.25 * float(before)
        assert bool(changed[0][flake].float().mean() > 0.8)
        # untouched pixels keep their texture exactly; the renders follow the new texture
        assert torch.equal(new[:, ~changed[0]], tex[:, ~changed[0]])
        args = (sc.normals, sc.lights, sc.intensities, sc.cameras, sc.size)
        expect = phong_render(new, sc.s, sc.alpha, *args)
        assert float((new_phong - expect).abs().max()) < 1e-5

    def test_no_detection_changes_nothing(self):
        sc = make_scene(64, 64, None, shots=6, seed=1)
        cap = _capture(sc)
        tex, phong = _least_squares_texture(sc)
        labels = torch.zeros(cap.num_shots, 64, 64, dtype=torch.int64)
        new, new_phong, changed = texture_without_glints(cap, tex, phong, labels)
        assert new is tex and new_phong is phong and not bool(changed.any())

    def test_pixel_detected_in_every_shot_is_filled_from_neighbours(self, flaky):
        sc, cap = flaky
        tex, phong = _least_squares_texture(sc)
        labels = torch.zeros(cap.num_shots, 128, 128, dtype=torch.int64)
        labels[:, 60:63, 60:63] = 1
        tex = tex.clone()
        tex[:, 50:72, 50:72] = 0.3  # flat neighbourhood, and a bright blob in the middle
        tex[:, 61, 61] = 0.9
        new, _, changed = texture_without_glints(cap, tex, phong, labels)
        assert bool(changed[0, 61, 61])
        assert torch.allclose(new[:, 61, 61], torch.full((3,), 0.3), atol=1e-6)
        assert torch.isfinite(new).all()

    def test_undetected_weak_glint_is_left_out(self):
        # a flake detected in shot 0 also glints below the threshold in shot 1: a mean over the
        # clean shots takes 1/7 of that glint into d(p) (and out of every detected glint)
        sc = make_scene(64, 64, None, shots=8, seed=5, noise=0.002, quantize=False)
        cap = _capture(sc)
        tex, _ = _least_squares_texture(sc)
        args = (sc.normals, sc.lights, sc.intensities, sc.cameras, sc.size)
        photos = sc.photos.clone()
        gain = phong_render(torch.ones_like(sc.texture), torch.zeros(3), sc.alpha, *args)
        photos[0, :, 30:33, 30:33] += 0.5 * gain[0, :, 30:33, 30:33]
        photos[1, :, 30:33, 30:33] += 0.1 * gain[1, :, 30:33, 30:33]  # weak: not detected
        cap = Capture(images=photos, normals=sc.normals, lights=sc.lights, intensities=sc.intensities,
                      cameras=sc.cameras, size=sc.size)
        tex = tex.clone()
        tex[:, 30:33, 30:33] += (0.5 + 0.1) / 8  # what the all-shot fit absorbed
        phong = phong_render(tex, sc.s, sc.alpha, *args)
        labels = torch.zeros(8, 64, 64, dtype=torch.int64)
        labels[0, 30:33, 30:33] = 1
        new, _, _ = texture_without_glints(cap, tex, phong, labels)
        err = (new - sc.texture)[:, 30:33, 30:33].abs().max()
        assert float(err) < 0.1 / 7 / 3  # within a third of what a clean-shot mean would keep

    def test_renders_change_only_where_the_texture_did_and_the_inputs_stay(self, flaky):
        """The renders are updated on the re-solved pixels only (elsewhere bit for bit the input's), the input
        renders are left as they were, and a float64 texture gives float64 renders."""
        sc, cap = flaky
        tex, phong = _least_squares_texture(sc)
        det = _detect(cap, phong)
        before = phong.clone()
        new, new_phong, changed = texture_without_glints(cap, tex.double(), phong, det.labels)
        assert torch.equal(phong, before) and new_phong.dtype == torch.float64 and new.dtype == torch.float64
        off = ~changed[0]
        assert torch.equal(new_phong[:, :, off], phong.double()[:, :, off])
        assert bool((new_phong[:, :, changed[0]] != phong.double()[:, :, changed[0]]).any())

    def test_deterministic(self, flaky):
        sc, cap = flaky
        tex, phong = _least_squares_texture(sc)
        det = _detect(cap, phong)
        a = texture_without_glints(cap, tex, phong, det.labels)
        b = texture_without_glints(cap, tex, phong, det.labels)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])

    def test_bad_shapes(self, flaky):
        sc, cap = flaky
        tex, phong = _least_squares_texture(sc)
        with pytest.raises(InputError, match="labels"):
            texture_without_glints(cap, tex, phong, torch.zeros(2, 128, 128, dtype=torch.int64))
        with pytest.raises(InputError, match="texture"):
            texture_without_glints(cap, tex[:, :10], phong, torch.zeros(8, 128, 128, dtype=torch.int64))


def test_glint_energy_share_counts_the_grown_detections_over_valid_observations():
    from torchmetal.flakes.estimate.texture import glint_energy_share
    from torchmetal.synth import synth_capture

    cap = synth_capture(size=16, shots=2, seed=0, noise=0.0, exposure=0.3).capture
    assert bool(cap.mask.all()) and not bool(cap.saturated.any())
    phong = cap.images.clone()
    phong[0, :, 5, 5] -= 0.5  # one glint: residual 0.5 in each channel
    phong[1] -= 0.01  # misfit everywhere in the other shot
    labels = torch.zeros(2, 16, 16, dtype=torch.int64)
    labels[0, 5, 5] = 1
    on, total = 3 * 0.25, 3 * 0.25 + 3 * 16 * 16 * 1e-4
    assert glint_energy_share(cap, phong, labels) == pytest.approx(on / total, rel=1e-5)
    sat = cap.saturated.clone()
    sat[0, :, 5, 5] = True  # a saturated observation is not counted
    assert glint_energy_share(replace(cap, saturated=sat), phong, labels) == pytest.approx(0.0, abs=1e-9)
    assert glint_energy_share(cap, cap.images, labels) == 0.0  # no residual
