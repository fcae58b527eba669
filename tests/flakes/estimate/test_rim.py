"""The mask's rim is left out of the screen and the null test (torchmetal.flakes.estimate.rim)."""

from dataclasses import replace
from types import SimpleNamespace

import torch

from torchmetal.flakes.estimate.prescreen import sampled_valid
from torchmetal.flakes.estimate.results import Particles
from torchmetal.flakes.estimate.rim import RIM, drop_rim, interior


def disc(h=40, w=50, r=15):
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    return (((yy - h / 2) ** 2 + (xx - w / 2) ** 2) <= r * r).view(1, h, w)


def test_interior_is_the_mask_eroded_by_the_rim():
    m = disc()
    inner = interior(m)
    assert bool((inner <= m).all()) and int(inner.sum()) < int(m.sum())
    # every interior pixel is more than RIM px (Chebyshev) from the outside, every dropped mask pixel within RIM
    out = torch.nonzero(~m[0]).float()
    for ij, want in ((torch.nonzero(inner[0]).float(), True), (torch.nonzero(m[0] & ~inner[0]).float(), False)):
        d = torch.cdist(ij, out, p=float("inf")).amin(1)
        assert bool(((d > RIM) == want).all())


def test_full_mask_and_image_border_have_no_rim():
    full = torch.ones(1, 12, 9, dtype=torch.bool)
    assert torch.equal(interior(full), full)
    half = full.clone()
    half[:, :, 6:] = False  # the outside is the right part; the image border is not outside
    inner = interior(half)
    assert bool(inner[0, :, : 6 - RIM].all()) and not bool(inner[0, :, 6 - RIM :].any())


def test_drop_rim_and_the_screen_look_inside_only():
    m = disc()
    ps = Particles.empty()
    cy = torch.tensor([20.0, 20.0, 20.0])
    cx = torch.tensor([25.0, 10.5, 36.0])  # centre, on the rim (left edge at x≈10), inside near the right edge
    n = 3
    cols = {f: torch.zeros((n, 3) if f in ("rgb", "lab", "peak") else (n,), dtype=torch.int64 if f == "shot"
                           else torch.float32) for f in ps.__dataclass_fields__}
    ps = replace(ps, **{**cols, "cy": cy, "cx": cx})
    kept, dropped = drop_rim(SimpleNamespace(mask=m), ps)
    assert dropped == 1 and kept.cx.tolist() == [25.0, 36.0]
    cap = SimpleNamespace(mask=m, saturated=torch.zeros(2, 3, 40, 50, dtype=torch.bool), num_shots=2)
    v = sampled_valid(cap, stride=1)
    assert v.shape == (2, 40, 50) and torch.equal(v[0], interior(m)[0])
