"""Property tests: fits on random scenes never return NaN/Inf."""

import math

import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchmetal.fit import fit_phong
from torchmetal.io.capture import Capture
from torchmetal.phong import phong_render


@st.composite
def scenes(draw):
    seed = draw(st.integers(0, 2**31 - 1))
    g = torch.Generator().manual_seed(seed)
    h, w = draw(st.integers(3, 10)), draw(st.integers(3, 10))
    n = draw(st.integers(1, 5))
    tex = torch.rand(3, h, w, generator=g) * draw(st.sampled_from([0.0, 0.1, 1.0]))
    s = torch.rand(3, generator=g) * draw(st.sampled_from([0.0, 0.5, 3.0]))
    alpha = torch.exp(torch.rand(3, generator=g) * math.log(draw(st.sampled_from([2.0, 100.0, 5000.0]))))
    directional = draw(st.booleans())
    xy = (torch.rand(n, 2, generator=g) - 0.5) * draw(st.sampled_from([0.0, 0.2, 2.0]))
    z = 0.02 + torch.rand(n, 1, generator=g) * 0.5
    lights = torch.cat([xy, z, torch.full((n, 1), 0.0 if directional else 1.0)], 1)
    cams = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 0.05, torch.full((n, 1), 0.3), torch.ones(n, 1)], 1)
    inten = torch.rand(n, 3, generator=g) * 0.05 * (1 if directional else 1.0)
    if draw(st.booleans()):
        inten[:, 1] = 0.0  # a dark channel
    normals = torch.zeros(3, h, w)
    normals[2] = 1.0
    if draw(st.booleans()):
        normals = torch.nn.functional.normalize(normals + 0.8 * torch.randn(3, h, w, generator=g), dim=0)
    img = phong_render(tex, s, alpha, normals, lights, inten, cams, (0.1, 0.1))
    img = (img + draw(st.sampled_from([0.0, 0.01])) * torch.randn(img.shape, generator=g)).clamp_min(0.0)
    sat = torch.rand(img.shape, generator=g) < draw(st.sampled_from([0.0, 0.2, 1.0]))
    mask = torch.rand(1, h, w, generator=g) < draw(st.sampled_from([1.0, 0.5]))
    cap = Capture(images=img, normals=normals, mask=mask, lights=lights, intensities=inten, cameras=cams,
                  size=(0.1, 0.1), saturated=sat)
    return cap, draw(st.sampled_from(["paper", "refine"])), draw(st.sampled_from(["auto", "global", "clustered"])), \
        draw(st.sampled_from([None, "huber", "cauchy"]))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenes())
def test_fits_never_return_nan_or_inf(scene):
    cap, scheme, specular, robust = scene
    if scheme == "paper" and specular == "clustered":
        specular = "global"
    f = fit_phong(cap, scheme=scheme, specular=specular, robust=robust, max_iters=30)
    for t in (f.texture, f.s, f.alpha):
        assert torch.isfinite(t).all()
    assert math.isfinite(f.rmse)
    assert bool((f.alpha >= 1.0).all()) and bool((f.s >= 0).all())
    if f.cluster_s is not None:
        assert torch.isfinite(f.cluster_s).all() and torch.isfinite(f.cluster_alpha).all()
    with torch.no_grad():
        assert torch.isfinite(f.render(cap.lights, cap.intensities, cap.cameras)).all()
    for h in f.history:
        assert math.isfinite(h["rmse"])
