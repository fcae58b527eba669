"""Observations: the decomposition I = a·d + s·b matches the renderer; chunking, strides, masks."""

import pytest
import torch

from tests.fit.helpers import replace, synth
from torchmetal.fit.problem import Reference, Weighting, build_observations, grid_stride
from torchmetal.fit.refine import model_terms
from torchmetal.phong import phong_render


def _render64(cap, tex, s, alpha):
    return phong_render(tex, s, alpha, cap.normals.double(), cap.lights.double(), cap.intensities.double(),
                        cap.cameras.double(), cap.size)


@pytest.mark.parametrize("bumpy", [True, False])  # per-pixel normals, and the flat fast path
def test_model_terms_reproduce_the_renderer_float64(bumpy):
    r = synth(size=16, shots=5, seed=3, bumpy=bumpy, layout="near")
    cap = r.capture.to(dtype=torch.float64)
    tex = r.truth["texture"].double()
    s = torch.tensor([0.3, 0.6, 1.2], dtype=torch.float64)
    alpha = torch.tensor([5.0, 60.0, 900.0], dtype=torch.float64)
    obs = build_observations(cap)
    assert obs.dtype == torch.float64
    a, b, _ = model_terms(obs, alpha.view(1, 3))
    got = (a * tex.reshape(1, 3, -1) + s.view(1, 3, 1) * b).reshape(5, 3, 16, 16)
    torch.testing.assert_close(got, _render64(cap, tex, s, alpha), rtol=1e-10, atol=1e-13)


def test_chunking_does_not_change_anything():
    cap = synth(size=20, shots=4, seed=1).capture
    ref = Reference(torch.tensor([[0.5, 0.5, 0.5]], dtype=torch.float64), torch.tensor([[30.0, 40.0, 50.0]], dtype=torch.float64))
    wt = Weighting(sigma=torch.tensor([0.01, 0.01, 0.01]), outlier_k=3.0)
    big = build_observations(cap, chunk=4096, ref=ref, weighting=wt, want_tmin=True)
    small = build_observations(cap, chunk=7, ref=ref, weighting=wt, want_tmin=True)
    assert len(small.chunks) > len(big.chunks)
    for name in ("g", "u", "L", "valid", "saa", "d0", "A", "n", "fallback", "tmin"):
        torch.testing.assert_close(getattr(small, name), getattr(big, name), rtol=1e-6, atol=1e-9)


def test_strided_grid_is_a_subsample_of_the_full_grid():
    cap = synth(size=21, shots=3, seed=2).capture
    full = build_observations(cap)
    sub = build_observations(cap, stride=4)
    off = 2
    idx = (torch.arange(off, 21, 4).view(-1, 1) * 21 + torch.arange(off, 21, 4).view(1, -1)).reshape(-1)
    assert sub.height == sub.width == len(range(off, 21, 4))
    torch.testing.assert_close(sub.L, full.L[:, :, idx])
    torch.testing.assert_close(sub.d0, full.d0[:, idx])
    assert grid_stride(1024, 1024, 1 << 16) == 4 and grid_stride(10, 10, 1 << 16) == 1


def test_shot_subset_matches_capture_subset():
    cap = synth(size=12, shots=5, seed=4).capture
    a = build_observations(cap, shots=[0, 3])
    b = build_observations(cap.subset([0, 3]))
    torch.testing.assert_close(a.g, b.g)
    torch.testing.assert_close(a.d0, b.d0)


def test_validity_mask_saturation_and_shadow():
    cap = synth(size=12, shots=4, seed=5, layout="far").capture
    mask = torch.ones_like(cap.mask)
    mask[:, :3] = False
    sat = torch.zeros_like(cap.saturated)
    sat[1, 0, 5, 5] = True
    normals = cap.normals.clone()
    normals[:, 8, 8] = torch.tensor([0.0, 0.0, -1.0])  # facing away: n·l < 0 in every shot
    cap2 = replace(cap, mask=mask, saturated=sat, normals=normals)
    obs = build_observations(cap2)
    v = obs.valid.bool().view(4, 3, 12, 12)
    assert not v[:, :, :3].any()
    assert not v[1, 0, 5, 5] and v[1, 1, 5, 5]
    assert not v[:, :, 8, 8].any()
    assert float(obs.saa.view(3, 12, 12)[:, 8, 8].abs().max()) == 0.0


def test_outliers_are_masked_at_the_reference():
    r = synth(size=16, shots=8, seed=6)
    cap = r.capture
    img = cap.images.clone()
    img[2, :, 4, 4] += 5.0  # a glint
    cap2 = replace(cap, images=img)
    ref = Reference(r.truth["s"].double().view(1, 3), r.truth["alpha"].double().view(1, 3))
    obs = build_observations(cap2, ref=ref, weighting=Weighting(sigma=torch.full((3,), 1e-3), outlier_k=5.0))
    v = obs.valid.bool().view(8, 3, 16, 16)
    assert not v[2, :, 4, 4].any()
    assert int((~obs.valid.bool()).sum()) == 3  # nothing else
    d = obs.d0.view(3, 16, 16)[:, 4, 4]
    spec_free = build_observations(cap, ref=ref, weighting=Weighting(sigma=torch.full((3,), 1e-3), outlier_k=5.0))
    torch.testing.assert_close(d, spec_free.d0.view(3, 16, 16)[:, 4, 4], rtol=0.2, atol=0.05)


@pytest.mark.parametrize("lobe", ["phong", "ggx"])
@pytest.mark.parametrize("weigh", [False, True])
def test_streamed_observations_equal_the_stored_ones(lobe, weigh):
    """stream=True recomputes every chunk's geometry and validity: the same values, pass by pass."""
    from torchmetal.fit.refine import spec_sums

    r = synth(size=20, shots=6, seed=7, bumpy=True, layout="near")
    mask = torch.ones_like(r.capture.mask)
    mask[:, :2] = False
    sat = torch.zeros_like(r.capture.saturated)
    sat[2, 1, 9, 4] = True
    cap = replace(r.capture, mask=mask, saturated=sat)
    ref = Reference(torch.tensor([[0.5, 0.4, 0.6]], dtype=torch.float64), torch.tensor([[30.0, 40.0, 50.0]], dtype=torch.float64))
    wt = Weighting(sigma=torch.full((3,), 0.01), robust="huber") if weigh else None
    kw = dict(chunk=37, ref=ref, weighting=wt, with_stats=True, lobe=lobe)  # 37: chunks straddle rows and blocks
    stored, streamed = build_observations(cap, **kw), build_observations(cap, stream=True, **kw)
    assert streamed.g is None and (streamed.valid is None) == (not weigh) and stored.g is not None
    for name in ("saa", "d0", "A", "n", "fallback", "lmax"):
        torch.testing.assert_close(getattr(streamed, name), getattr(stored, name), rtol=0, atol=0)
    for x, y in zip(streamed.first_stats, stored.first_stats):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    shots = torch.tensor([1, 4])
    for j in (0, 5, len(stored.chunks) - 1):
        for sub in (None, shots):
            for x, y in zip(streamed.chunk(j, sub), stored.chunk(j, sub)):
                torch.testing.assert_close(x, y, rtol=0, atol=0)
            gs, gd = streamed.geo_chunk(j, sub), stored.geo_chunk(j, sub)
            assert (gs is None) == (gd is None) == (lobe == "phong")
            if gs is not None:
                torch.testing.assert_close(gs, gd, rtol=0, atol=0)
    alpha = torch.tensor([[25.0, 45.0, 70.0]], dtype=torch.float64)
    for x, y in zip(spec_sums(streamed, alpha)[:2], spec_sums(stored, alpha)[:2]):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    for x, y in zip(streamed.dense(), stored.dense()):
        if x is not None:
            torch.testing.assert_close(x, y, rtol=0, atol=0)


@pytest.mark.parametrize("robust", [None, "cauchy"])
def test_energy_is_the_weighted_sum_of_squares(robust):
    """energy() = Σ w·y² per element, derived as A + saa·d0² (no stored map), in blocks."""
    import torchmetal.fit.problem as problem

    cap = synth(size=20, shots=5, seed=8).capture.to(dtype=torch.float64)
    ref = Reference(torch.tensor([[0.5, 0.4, 0.6]], dtype=torch.float64), torch.tensor([[30.0, 40.0, 50.0]], dtype=torch.float64))
    wt = Weighting(sigma=torch.full((3,), 0.01), robust=robust) if robust else None
    obs = build_observations(cap, ref=ref, weighting=wt, chunk=64)
    direct = torch.zeros(3, obs.num_pixels, dtype=torch.float64)
    for j, (p0, p1) in enumerate(obs.chunks):
        y, _, _, _, w, _ = obs.chunk(j)
        direct[:, p0:p1] = (w * y * y).sum(0)
    obs.labels = torch.arange(obs.num_pixels) % 3
    old = problem.SUM_BLOCK
    try:
        problem.SUM_BLOCK = 50  # several blocks
        torch.testing.assert_close(obs.energy(), direct.sum(-1).view(1, 3), rtol=1e-12, atol=0)
        torch.testing.assert_close(obs.energy(3), obs.element_sum(direct, 3), rtol=1e-12, atol=0)
    finally:
        problem.SUM_BLOCK = old
