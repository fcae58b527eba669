"""Flake statistics (torchmetal.flakes.estimate.stats and the modules it builds on: association,
glint_model, likelihood, visibility): accuracy against synthetic truth, flake-free captures,
determinism, the glint likelihood's pieces and bad input.

Scenes are 384² with 10 shots at density 0.01 (~1,500 flakes, 450–600 detected): the
estimator's own noise is then ~3–4 % on density and tilt and ~0.02 on the colour mean, well
inside the tolerances. Every case runs the same default parameters.
"""

import math
from dataclasses import replace

import pytest
import torch

from tests.flakes.scenes import capture_of, make_scene, true_flakes
from torchmetal.errors import InputError
from torchmetal.flakes.estimate import association, glint_model, likelihood, shot_geometry, visibility
from torchmetal.flakes.estimate import stats as S
from torchmetal.flakes.estimate.detect import detect_flakes
from torchmetal.flakes.model import MAX_DENSITY, FlakeModel
from torchmetal.flakes.stage import flake_stage

SIZE, SHOTS, DENSITY = 384, 10, 0.01
TRUE = dict(area_log_mean=math.log(6.0), area_log_std=0.35, tilt_sigma=0.15, glint_sigma=0.03, color_mean=(0.7, 0.6, 0.4))
CASES = [  # (seed, texture, bumpy normals, layout)
    (0, "noise", False, "pairs"),
    (1, "checker", False, "pairs"),
    (2, "stripes", False, "pairs"),
    (3, "checker", True, "pairs"),
    (4, "noise", False, "flash"),
]


def true_model(seed: int) -> FlakeModel:
    return FlakeModel(density=DENSITY, seed=seed, **TRUE)


@pytest.fixture(scope="module", params=CASES, ids=lambda c: f"seed{c[0]}-{c[1]}-{c[3]}{'-bumpy' if c[2] else ''}")
def fitted(request):
    seed, texture, bumpy, kind = request.param
    m = true_model(seed)
    sc = make_scene(SIZE, SIZE, m, texture=texture, bumpy=bumpy, kind=kind, shots=SHOTS, seed=seed)
    res = flake_stage(capture_of(sc), sc.phong, seed=seed)
    return sc, m, res, true_flakes(m, SIZE, SIZE, sc.normals)


class TestAccuracy:
    def test_density_within_10_percent(self, fitted):
        sc, m, res, truth = fitted
        assert res.model is not None, res.report.get("skipped")
        # compared with the realised density (flakes actually in the field / area): the field
        # draws each cell's flake at random, so the realised count differs from the model
        # density by its own Poisson noise (~2.6 % here), which the estimator cannot see
        realised = truth["count"] / (SIZE * SIZE)
        assert abs(res.model.density / realised - 1) < 0.10

    def test_median_area_within_15_percent(self, fitted):
        _, m, res, _ = fitted
        assert abs(res.model.median_area / m.median_area - 1) < 0.15

    def test_colour_mean_within_0_05(self, fitted):
        # (the flash layout, where flakes glint in many shots, was 0.075 off while the
        # likelihood anchored each flake on its brightest detection)
        _, m, res, truth = fitted
        # linear reflectance, max abs over channels, against the mean colour of the flakes
        # actually drawn (the per-flake colour spread is 0.1 per channel)
        realised = truth["color"].mean(0)
        err = (torch.tensor(res.model.color_mean) - realised).abs().max()
        assert float(err) < 0.05

    def test_tilt_sigma_within_20_percent(self, fitted):
        _, m, res, _ = fitted
        assert abs(res.model.tilt_sigma / m.tilt_sigma - 1) < 0.20

    def test_glint_sigma_identified(self, fitted):
        _, m, res, _ = fitted
        assert res.report["identified"]["log_glint_sigma"]
        assert abs(res.model.glint_sigma / m.glint_sigma - 1) < 0.25


class TestFlakeFree:
    @pytest.mark.parametrize("seed,texture,bumpy,kind", [CASES[0], CASES[3], CASES[4]])
    def test_no_flakes_reported(self, seed, texture, bumpy, kind):
        sc = make_scene(SIZE, SIZE, None, texture=texture, bumpy=bumpy, kind=kind, shots=SHOTS, seed=seed)
        res = flake_stage(capture_of(sc), sc.phong, seed=seed)
        assert res.model is None
        assert "skipped" in res.report and res.report["flakes_detected"] < res.report["flakes_needed"]  # noise
        # false positives: associated detections per pixel, ≈ 0
        assert res.report["flakes_detected"] / (SIZE * SIZE) < 2e-4


@pytest.fixture(scope="module")
def small():
    """(detection, geometry) of a 256² 8-shot scene."""
    sc = make_scene(256, 256, true_model(6), shots=8, seed=6)
    det = detect_flakes(sc.photos, sc.phong, sc.irradiance, valid=sc.valid)
    return det, shot_geometry.Geometry(sc.normals, sc.lights, sc.intensities, sc.cameras, sc.size)


@pytest.fixture(scope="module")
def data(small):
    det, geo = small
    h, w = det.signal.shape[-2:]
    fid, count = association.associate(det.particles, h, w)
    obs = association.observe(det, fid, count, geo)
    gh, gn, gs, ga, _ = visibility.cell_grid(det, geo, 36, association.measurable(det))
    return glint_model.GlintData(
        half=obs.half.double(), normal=obs.normal.double(), anchor=obs.anchor, amp=obs.amp.double(),
        detected=obs.detected, sigma=obs.sigma.double(), grid_half=gh, grid_normal=gn, grid_sigma=gs,
        grid_area=ga, k_hi=det.k_hi, count=count,
    )


class TestDeterminism:
    def test_same_inputs_same_model(self, small):
        det, geo = small
        a = S.flake_statistics(det, geo, seed=5)
        b = S.flake_statistics(det, geo, seed=5)
        assert a.model is not None
        da, db = a.model.to_dict(), b.model.to_dict()
        assert da == db, {k: (da[k], db[k]) for k in da if da[k] != db[k]}
        assert torch.equal(a.flake_id, b.flake_id)


PARAMS = dict(tau=torch.tensor(0.15), sg=torch.tensor(0.03), la=torch.tensor(math.log(0.57)), va=torch.tensor(0.1))


class TestLikelihood:
    def test_log_detect_far_non_detection_is_free(self):
        # a shot whose cap is far from the flake (P = 0) must add exactly 0, whatever the
        # outlier mix: which far shots are included changes with the parameters
        z = torch.tensor([-50.0, 0.0, 50.0])
        no = torch.zeros(3, dtype=torch.bool)
        lp = glint_model.log_detect(z, 5.0, no, outlier=0.02)
        assert float(lp[0]) == pytest.approx(0.0, abs=1e-9)
        assert float(lp[2]) == pytest.approx(math.log(0.01 / 0.99), rel=1e-3)  # a certain miss: bounded
        assert float(glint_model.log_detect(z, 5.0, ~no, outlier=0.02)[0]) == pytest.approx(math.log(0.01), rel=1e-3)

    def test_extra_far_shot_leaves_numerator_unchanged(self, data):
        p = {k: v.double() for k, v in PARAMS.items()}
        base = likelihood.log_numerator(data, p["tau"], p["sg"], p["la"], p["va"])
        # one more shot whose half vector points far away (never detected)
        j = data.amp.shape[0]
        far = torch.tensor([0.6, 0.0, 0.8], dtype=torch.float64).expand(j, 1, 3)
        more = glint_model.GlintData(
            torch.cat([data.half, far], 1), data.normal, data.anchor, data.amp,
            torch.cat([data.detected, torch.zeros(j, 1, dtype=torch.bool)], 1),
            torch.cat([data.sigma, data.sigma[:, :1]], 1), data.grid_half, data.grid_normal, data.grid_sigma,
            data.grid_area, data.k_hi, data.count,
        )
        torch.testing.assert_close(likelihood.log_numerator(more, p["tau"], p["sg"], p["la"], p["va"]), base, rtol=0, atol=1e-9)

    def test_numerator_matches_vector_reference(self, data):
        # the projected ring nodes equal the explicit (J, nA, nφ, 3) construction for one shot
        p = {k: v.double() for k, v in PARAMS.items()}
        one = glint_model.GlintData(
            data.half[:, :1], data.normal, torch.zeros_like(data.anchor), data.amp, data.detected[:, :1],
            data.sigma[:, :1], data.grid_half, data.grid_normal, data.grid_sigma, data.grid_area, data.k_hi, data.count,
        )
        got = likelihood.log_numerator(one, p["tau"], p["sg"], p["la"], p["va"], n_a=4, n_phi=8)
        j = one.amp.shape[0]
        qa, phi = glint_model.ring_nodes(4, 8, torch.float64, "cpu")
        h = one.half[:, 0]
        e1, e2 = glint_model.orthonormal_pair(h)
        t1, t2 = glint_model.orthonormal_pair(one.normal)
        la_hat = torch.log(one.amp)
        z0 = (la_hat - p["la"]) / p["va"]
        tail = torch.exp(torch.special.log_ndtr(-z0)).unsqueeze(1) * (1 - qa)
        z = torch.maximum(-torch.special.ndtri(tail), z0.unsqueeze(1))
        cap = (p["sg"] ** 2 * (p["la"] + p["va"] * z - la_hat.unsqueeze(1))).clamp(1e-9, 1.9)
        ring = torch.cos(phi).view(1, 1, -1, 1) * e1.view(j, 1, 1, 3) + torch.sin(phi).view(1, 1, -1, 1) * e2.view(j, 1, 1, 3)
        m = (1 - cap).view(j, 4, 1, 1) * h.view(j, 1, 1, 3) + torch.sqrt(cap * (2 - cap)).view(j, 4, 1, 1) * ring
        logp = glint_model._log_slope_density(m, one.normal.view(j, 1, 1, 3), t1.view(j, 1, 1, 3), t2.view(j, 1, 1, 3), p["tau"])
        logw = torch.special.log_ndtr(-z0).view(j, 1, 1) - math.log(4) + math.log(2 * math.pi / 8)
        ref = torch.logsumexp((logp + logw).flatten(1), 1) + 2 * torch.log(p["sg"]) - la_hat
        torch.testing.assert_close(got, ref, rtol=1e-9, atol=1e-9)

    @staticmethod
    def _p_any_reference(d, cell, tau, sg, la, va, samples=40000, n_amp=120):
        """P_any of one grid cell by brute force: slopes drawn from N(0, τ²I), log A on a dense
        grid above the floor, detection Φ(A·g/σ − k_hi) (the probit the logistic stands for)."""
        gen = torch.Generator().manual_seed(0)
        mu = torch.randn(samples, 2, generator=gen, dtype=torch.float64) * tau
        n = d.grid_normal[cell]
        t1, t2 = glint_model.orthonormal_pair(n)
        m = n + mu[:, :1] * t1 + mu[:, 1:] * t2
        mh = (m / m.norm(dim=-1, keepdim=True)) @ d.grid_half[cell].t()  # (S, N)
        floor = glint_model.log_amp_floor(d)
        xs = torch.linspace(floor, max(la + 8 * va, floor + 3), n_amp, dtype=torch.float64)
        dens = torch.exp(-0.5 * ((xs - la) / va) ** 2) / (va * math.sqrt(2 * math.pi))
        vals = torch.stack([
            (1 - (1 - torch.special.ndtr(torch.exp(x - (1 - mh) / sg**2) / d.grid_sigma[cell] - d.k_hi)).prod(-1)).mean()
            for x in xs
        ])
        return float(torch.trapezoid(vals * dens, xs) / torch.special.ndtr(torch.tensor(-(floor - la) / va)))

    @pytest.mark.parametrize("prm", [(0.15, 0.03, math.log(0.57), 0.1), (0.06, 0.05, -2.0, 0.3), (0.06, 0.05, -10.0, 2.0)],
                             ids=["truth", "wide-glint", "far-amplitude-tail"])
    def test_p_any_matches_brute_force(self, data, prm):
        # the far tail (most flakes below the noise, a few bright ones) is where quantile nodes
        # in A were 17-37x off and the fit ran away on cards_blue
        t = {k: torch.tensor(v, dtype=torch.float64) for k, v in zip(("tau", "sg", "la", "va"), prm)}
        got = visibility.log_p_any(data, t["tau"], t["sg"], t["la"], t["va"]).exp()
        for cell in (0, 14, 35):
            ref = self._p_any_reference(data, cell, *prm)
            assert float(got[cell]) == pytest.approx(ref, rel=0.12, abs=1e-5), cell

    def test_p_any_far_tail_does_not_underflow_float32(self, data):
        # a far tail's weight is below float32's range: the fit ran off to "no flake expected
        # anywhere" when it underflowed to 0
        d64 = replace(data, log_floor=glint_model.log_amp_floor(data))
        grid32 = S._recast(d64, None, torch.float32, flakes=False, grid=True)
        la, va = -40.0, 1.8
        assert math.log(0.5 * math.erfc((d64.log_floor - la) / va / math.sqrt(2))) < math.log(1e-38)  # a far tail
        args = [torch.tensor(v) for v in (0.06, 0.05, la, va)]
        lp32 = visibility.log_p_any(grid32, *[a.float() for a in args])
        lp64 = visibility.log_p_any(d64, *[a.double() for a in args])
        assert lp32.dtype == torch.float64 and bool(torch.isfinite(lp32).all())
        torch.testing.assert_close(lp32, lp64, rtol=0, atol=0.05)

    def test_truncated_moments_match_quadrature(self):
        for mu, v, floor in ((-0.5, 0.1, -3.0), (-10.0, 2.0, -6.0), (-2.0, 0.5, -1.5)):
            x = torch.linspace(floor, mu + 12 * v + abs(floor - mu), 200001, dtype=torch.float64)
            w = torch.exp(-0.5 * ((x - mu) / v) ** 2)
            a = torch.exp(x)
            m1 = float(torch.trapezoid(w * a, x) / torch.trapezoid(w, x))
            m2 = float(torch.trapezoid(w * a * a, x) / torch.trapezoid(w, x))
            got_m, got_v = glint_model.truncated_moments(mu, v, floor)
            assert got_m == pytest.approx(m1, rel=1e-4)
            assert got_v == pytest.approx(m2 - m1 * m1, rel=1e-3)

    def test_fit_recovers_truth_and_reports(self, data):
        fit = S.fit_glints(data)
        assert abs(fit.tilt_sigma / 0.15 - 1) < 0.25 and abs(fit.glint_sigma / 0.03 - 1) < 0.25
        assert fit.iterations > 0 and fit.evaluations >= fit.iterations
        assert set(fit.std_err) == set(fit.identified) == {"log_tilt_sigma", "log_glint_sigma", "log_amp_mean", "log_amp_std"}
        assert all(math.isfinite(v) for v in fit.std_err.values())

    def test_glint_width_stays_put_without_multi_shot_flakes(self, data):
        # every flake seen in one shot only (e.g. a one-shot capture): nothing sets σ_g
        one = torch.zeros_like(data.detected)
        one[torch.arange(one.shape[0]), data.anchor] = True
        fit = S.fit_glints(replace(data, detected=one))
        assert fit.glint_sigma == pytest.approx(0.03, rel=1e-12)
        assert not fit.identified["log_glint_sigma"] and math.isnan(fit.std_err["log_glint_sigma"])
        assert fit.identified["log_tilt_sigma"] and math.isfinite(fit.std_err["log_tilt_sigma"])
        assert math.isfinite(fit.density) and fit.density > 0

    def test_fit_does_not_modify_init(self, data):
        init = {"glint_sigma": 0.03}
        S.fit_glints(data, init=init, uncertainty=False)
        assert init == {"glint_sigma": 0.03}

    def test_fit_keeps_thread_count(self, data):
        before = torch.get_num_threads()
        with S._one_thread():
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == before


class TestBadInput:
    def test_no_flakes(self, data):
        empty = glint_model.GlintData(
            data.half[:0], data.normal[:0], data.anchor[:0], data.amp[:0], data.detected[:0], data.sigma[:0],
            data.grid_half, data.grid_normal, data.grid_sigma, data.grid_area, data.k_hi, 0,
        )
        with pytest.raises(InputError, match="at least one associated flake"):
            S.fit_glints(empty)

    def test_geometry_shot_count(self):
        sc = make_scene(64, 64, true_model(0), shots=4, seed=0)
        det = detect_flakes(sc.photos, sc.phong, sc.irradiance)
        geo = shot_geometry.Geometry(sc.normals, sc.lights[:3], sc.intensities[:3], sc.cameras[:3], sc.size)
        with pytest.raises(InputError, match="expected 4 shots"):
            S.flake_statistics(det, geo)


class TestDegenerateFit:
    def test_runaway_density_is_skipped_not_rendered(self, small, monkeypatch):
        """A likelihood that runs off (density → ∞) gives no model."""
        det, geo = small
        real = S.fit_glints

        def runaway(*args, **kwargs):
            fit = real(*args, **kwargs)
            fit.density = math.inf
            return fit

        monkeypatch.setattr(S, "fit_glints", runaway)
        res = S.flake_statistics(det, geo)
        assert res.model is None
        assert "skipped" in res.report and res.report["degenerate"]["density"] == math.inf

    @pytest.mark.parametrize("fitted_density,model_density", [(0.2, MAX_DENSITY), (2.0, None)])
    def test_dense_layer_is_rendered_at_capacity(self, small, monkeypatch, fitted_density, model_density):
        """Denser than the hash field can draw (≤ 1/px): rendered at capacity and said so;
        more flakes than pixels: degenerate."""
        det, geo = small
        real = S.fit_glints

        def dense(*args, **kwargs):
            fit = real(*args, **kwargs)
            fit.density = fitted_density
            return fit

        monkeypatch.setattr(S, "fit_glints", dense)
        res = S.flake_statistics(det, geo)
        if model_density is None:
            assert res.model is None and "skipped" in res.report and res.report["degenerate"]["density"] == fitted_density
            return
        assert res.model.density == model_density
        assert res.model.extra["density_fitted"] == fitted_density == res.report["density"]
        assert "density_clamped" in res.report and res.report["density_rendered"] == MAX_DENSITY < res.report["density"]


class TestBoundedEstimates:
    """Every estimate of the glint fit stays in a box the data can speak to (colours of 1e20 came from an
    unidentified amplitude spread extrapolated above every detection)."""

    def test_moments_with_a_ceiling_match_quadrature(self):
        for mu, v, floor, ceil in ((-0.5, 0.1, -3.0, 0.5), (-2.0, 1.5, -6.0, 0.0), (3.0, 6.0, -6.0, 2.0)):
            x = torch.linspace(floor, ceil, 400001, dtype=torch.float64)
            w = torch.exp(-0.5 * ((x - mu) / v) ** 2)
            a = torch.exp(x)
            m1 = float(torch.trapezoid(w * a, x) / torch.trapezoid(w, x))
            m2 = float(torch.trapezoid(w * a * a, x) / torch.trapezoid(w, x))
            got_m, got_v = glint_model.truncated_moments(mu, v, floor, ceil)
            assert got_m == pytest.approx(m1, rel=1e-4)
            assert got_v == pytest.approx(m2 - m1 * m1, rel=1e-3, abs=1e-12)
            assert math.exp(floor) <= got_m <= math.exp(ceil)

    def test_runaway_spread_gives_a_bounded_colour(self):
        """A spread of 6 (e^18 without the ceiling) keeps the mean below the ceiling."""
        m, var = glint_model.truncated_moments(0.0, 6.0, -5.0, 1.0)
        unbounded, _ = glint_model.truncated_moments(0.0, 6.0, -5.0)
        assert unbounded > 1e6 and m <= math.e and var <= math.e**2

    def test_all_mass_outside_the_box_sits_at_the_nearer_end(self):
        for mu in (50.0, 5000.0):
            m, var = glint_model.truncated_moments(mu, 0.1, -5.0, 1.0)
            assert m == pytest.approx(math.e, rel=1e-3) and 0.0 <= var < 1e-4

    def test_fit_stays_in_its_box(self, data):
        fit = S.fit_glints(data, init={"tau": 50.0, "glint_sigma": 1e-6, "log_amp": 80.0, "log_amp_std": 40.0},
                           uncertainty=False)
        assert S.TILT_RANGE[0] <= fit.tilt_sigma <= S.TILT_RANGE[1]
        assert S.GLINT_RANGE[0] <= fit.glint_sigma <= S.GLINT_RANGE[1]
        assert S.SPREAD_RANGE[0] <= fit.log_amp_std <= S.SPREAD_RANGE[1]
        assert fit.log_amp_floor <= fit.log_amp_mean <= fit.log_amp_ceiling
        assert fit.log_amp_ceiling == pytest.approx(float(torch.log(data.amp.double()).max()) + S.CEILING_MARGIN)

    def test_degenerate_likelihood_stops_early(self, data, monkeypatch):
        """A best point that needs more flakes than pixels ends the L-BFGS runs at once, without curvature."""
        monkeypatch.setattr(S, "DEGENERATE_DENSITY", 1e-12)  # every point degenerate
        fit = S.fit_glints(data)
        assert fit.degenerate is not None and fit.evaluations == S.DEGENERATE_AFTER
        assert all(math.isnan(v) for v in fit.std_err.values())

    def test_tilt_at_its_bound_stops_early(self, data, monkeypatch):
        """A best point with the flakes' tilt σ at the box's upper end (normals at random) is no flake layer."""
        monkeypatch.setattr(S, "TILT_RANGE", (0.01, 0.011))  # the box's top below any start: every point on it
        fit = S.fit_glints(data)
        assert fit.degenerate is not None and "at its bound" in fit.degenerate
        assert fit.evaluations == S.DEGENERATE_AFTER and fit.tilt_sigma == pytest.approx(0.011)

    def test_degenerate_fit_gives_no_model_and_says_why(self, small, monkeypatch):
        det, geo = small
        monkeypatch.setattr(S, "DEGENERATE_DENSITY", 1e-12)
        res = S.flake_statistics(det, geo)
        assert res.model is None and res.report["degenerate"]["evaluations"] == S.DEGENERATE_AFTER

    def test_a_model_the_checks_refuse_is_no_model_with_its_reason(self, small, monkeypatch):
        det, geo = small
        monkeypatch.setattr(S, "fit_colour", lambda obs, fit, **kw: ((1e21, 1e21, 1e21), ((1.0, 0, 0), (0, 1.0, 0), (0, 0, 1.0))))
        res = S.flake_statistics(det, geo)
        # fitted, not degenerate, then refused by the model's own checks: the MaterialError's one-line reason
        assert res.model is None and "density" in res.report and "degenerate" not in res.report and "skipped" in res.report
        assert "color_mean" in res.report["skipped"]
