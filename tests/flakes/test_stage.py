"""The flake stage (torchmetal.flakes.stage): one call from capture + Phong renders to a model."""

import math

import pytest
import torch

from tests.flakes.scenes import capture_of, make_scene
from torchmetal.errors import InputError
from torchmetal.flakes.estimate.results import FlakeStageResult
from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.stage import flake_stage, irradiance_maps

MODEL = FlakeModel(density=0.01, area_log_mean=math.log(6.0), area_log_std=0.35, tilt_sigma=0.15, glint_sigma=0.03,
                   color_mean=(0.7, 0.6, 0.4), seed=2)


@pytest.fixture(scope="module")
def scene():
    return make_scene(192, 192, MODEL, shots=6, seed=2)


@pytest.fixture(scope="module")
def result(scene):
    return flake_stage(capture_of(scene), scene.phong, seed=7)


class TestFlakeStage:
    def test_result_and_report(self, scene, result):
        assert isinstance(result, FlakeStageResult)
        assert result.model is not None and result.model.seed == 7
        rep = result.report
        for key in ("detect", "statistics", "statistics.likelihood", "total"):
            assert rep["times"][key] >= 0.0
        assert rep["times"]["total"] >= rep["times"]["detect"] + rep["times"]["statistics"] - 1e-9
        assert sum(rep["particles_per_shot"]) == len(result.particles)
        assert len(rep["particles_per_shot"]) == scene.photos.shape[0]
        assert result.flake_id.shape == (len(result.particles),)
        assert int(result.flake_id.max()) + 1 == rep["flakes_detected"]

    def test_irradiance_matches_scene(self, scene):
        torch.testing.assert_close(irradiance_maps(capture_of(scene)), scene.irradiance, rtol=1e-5, atol=1e-6)

    def test_stats_options_reach_the_statistics(self, scene, result):
        res = flake_stage(capture_of(scene), scene.phong, stats={"min_flakes": 10 * result.report["flakes_detected"]})
        assert res.model is None
        assert "skipped" in res.report and res.report["flakes_detected"] < res.report["flakes_needed"]
        assert res.report["flakes_needed"] >= 10 * result.report["flakes_detected"]
        assert res.report["particles_per_shot"] == result.report["particles_per_shot"]

    def test_bad_phong_shape(self, scene):
        with pytest.raises(InputError, match="phong_images"):
            flake_stage(capture_of(scene), scene.phong[:, :, :-1])


class TestGlintNull:
    """glint_excess / detect_capture(mirrored=True): glints exceed their mirror; symmetric misfit does not."""

    def test_glints_exceed_the_mirror(self, scene):
        from torchmetal.flakes.estimate.null_test import glint_excess
        from torchmetal.flakes.stage import detect_capture

        cap = capture_of(scene)
        kept, counts = glint_excess(detect_capture(cap, scene.phong).particles,
                                    detect_capture(cap, scene.phong, mirrored=True).particles,
                                    tuple(cap.images.shape[-2:]))
        assert kept and counts["positive"][0] > 2 * counts["mirrored"][0] + 10, counts

    def test_symmetric_misfit_is_not_glints(self, scene):
        """Bright and dark specks in equal numbers (a misfit of either sign) give no excess."""
        from dataclasses import replace

        from torchmetal.flakes.estimate.null_test import glint_excess
        from torchmetal.flakes.stage import detect_capture

        cap = capture_of(scene)
        g = torch.Generator().manual_seed(5)
        n, _, h, w = cap.images.shape
        specks = torch.zeros(n, 1, h, w)
        idx = torch.randint(0, h * w, (n, 120), generator=g)
        sign = torch.where(torch.rand(n, 120, generator=g) < 0.5, -1.0, 1.0)
        specks.view(n, -1).scatter_(1, idx, 0.15 * sign)
        photo = (scene.phong + specks * scene.irradiance).clamp_min(0.0)
        cap2 = replace(cap, images=photo)
        kept, counts = glint_excess(detect_capture(cap2, scene.phong).particles,
                                    detect_capture(cap2, scene.phong, mirrored=True).particles, (h, w))
        assert not kept and counts["positive"][0] > 50, counts  # plenty detected, none in excess


def test_extended_detections_are_left_out_of_the_null_test():
    from torchmetal.flakes.estimate.null_test import EXTENT, drop_extended
    from torchmetal.flakes.estimate.results import Particles

    p = Particles.empty()
    p = Particles(**{k: torch.zeros((4, *v.shape[1:]), dtype=v.dtype) for k, v in vars(p).items()})
    p.major = torch.tensor([2.0, EXTENT, EXTENT + 0.5, 200.0])
    p.shot = torch.tensor([0, 1, 2, 3])
    kept, dropped = drop_extended(p)
    assert dropped == 2 and kept.shot.tolist() == [0, 1]
