"""The pixel screen before the flake stage: noise and misfit fail it, glints pass it."""

import pytest
import torch

from torchmetal.flakes.estimate.prescreen import glint_screen

N, H, W = 8, 96, 96


def _screen(photo, phong, valid, **kw):
    return glint_screen((photo - phong.to(photo.dtype)).sum(1), valid[:, 0], **kw)


def _scene(seed: int = 0, noise: float = 0.01):
    g = torch.Generator().manual_seed(seed)
    phong = 0.2 + 0.3 * torch.rand(N, 3, 1, 1, generator=g).expand(N, 3, H, W).clone()
    photo = phong + noise * phong * torch.randn(N, 3, H, W, generator=g)
    return g, photo, phong, torch.ones(N, 1, H, W, dtype=torch.bool)


def _spikes(g, count: int, amp: float, size: int = 2) -> torch.Tensor:
    out = torch.zeros(N, 3, H, W)
    for _ in range(count):
        k = int(torch.randint(N, (1,), generator=g))
        i, j = (int(v) for v in torch.randint(4, H - 4, (2,), generator=g))
        out[k, :, i : i + size, j : j + size] = amp
    return out


def test_noise_alone_fails():
    _, photo, phong, valid = _scene()
    passed, counts = _screen(photo, phong, valid)
    assert not passed, counts
    assert counts["pixels"] == N * H * W
    assert _screen(photo, phong, valid, stride=2)[1]["pixels"] == N * (H // 2) * (W // 2)


def test_glints_pass_and_their_mirror_fails():
    g, photo, phong, valid = _scene(1)
    glints = _spikes(g, 40, 0.5)
    passed, counts = _screen(photo + glints, phong, valid)
    assert passed, counts
    assert counts["positive"][-1] >= 30  # bright: still counted at the top rung
    mirrored, counts = _screen(photo - glints, phong, valid)
    assert not mirrored, counts


def test_bright_glints_dig_no_negative_halo():
    g, photo, phong, valid = _scene(2)
    passed, counts = _screen(photo + _spikes(g, 30, 20.0, size=1), phong, valid)
    assert passed, counts
    assert counts["negative"][0] <= 3, counts


def test_smooth_misfit_is_not_a_glint():
    # a highlight of the wrong width: a wide bump of both signs, far above the noise
    _, photo, phong, valid = _scene(3)
    yy, xx = torch.meshgrid(torch.arange(H).float(), torch.arange(W).float(), indexing="ij")
    bump = torch.exp(-((yy - 48) ** 2 + (xx - 40) ** 2) / (2 * 10.0**2)) - torch.exp(-((yy - 48) ** 2 + (xx - 60) ** 2) / (2 * 6.0**2))
    passed, counts = _screen(photo + 0.5 * bump, phong, valid)
    assert not passed, counts


def test_masked_glints_do_not_count():
    g, photo, phong, valid = _scene(4)
    glints = _spikes(g, 40, 0.5)
    valid = valid & ~(glints > 0).any(1, keepdim=True)
    passed, counts = _screen(photo + glints, phong, valid)
    assert not passed, counts


@pytest.mark.parametrize("dtype", [torch.float16, torch.float64])
def test_dtypes_give_the_same_decision(dtype):
    g, photo, phong, valid = _scene(5)
    photo = photo + _spikes(g, 40, 0.5)
    passed, _ = _screen(photo.to(dtype), phong.to(dtype), valid)
    assert passed


@pytest.mark.parametrize("lobe", ["phong", "blinn", "ggx"])
@pytest.mark.parametrize("bumpy", [False, True])
@pytest.mark.parametrize("maps", [False, True])
@pytest.mark.parametrize("dull", [False, True])
def test_sampled_residual_is_the_strided_render_residual(lobe, bumpy, maps, dull):
    """The separable, channel-summed residual equals photo − fit.render on the strided pixels
    (``dull``: s = 0, the screen renders no lobe)."""
    from types import SimpleNamespace

    import torch.nn.functional as F

    from torchmetal.fit.result import FitResult
    from torchmetal.flakes.estimate.prescreen import sampled_residual

    g = torch.Generator().manual_seed(7)
    h, w, n = 37, 30, 5
    normals = torch.zeros(3, h, w)
    normals[2] = 1.0
    if bumpy:
        normals = F.normalize(normals + 0.2 * torch.randn(3, h, w, generator=g), dim=0)
    s, alpha = torch.tensor([0.4, 0.5, 0.6]) * (not dull), torch.tensor([30.0, 60.0, 90.0])
    extra = {}
    if maps:
        extra = dict(gloss_s=s[:, None, None] * (0.5 + torch.rand(3, h, w, generator=g)),
                     gloss_alpha=alpha[:, None, None] * (0.5 + torch.rand(3, h, w, generator=g)))
    fit = FitResult(texture=torch.rand(3, h, w, generator=g), s=s, alpha=alpha, normals=normals, size=(0.1, 0.12),
                    lobe=lobe, **extra)
    lights = torch.cat([0.3 * torch.randn(n, 2, generator=g), 0.2 + 0.2 * torch.rand(n, 1, generator=g),
                        torch.ones(n, 1)], 1)
    lights[0] = torch.tensor([0.1, 0.2, 0.9, 0.0])  # a directional light
    cams = torch.cat([0.05 * torch.randn(n, 2, generator=g), torch.full((n, 1), 0.4), torch.ones(n, 1)], 1)
    inten = 0.02 + 0.02 * torch.rand(n, 3, generator=g)
    images = torch.rand(n, 3, h, w, generator=g)
    cap = SimpleNamespace(images=images, lights=lights, intensities=inten, cameras=cams, num_shots=n)
    want = (images - fit.render(lights, inten, cams))[..., ::2, ::2].sum(1)
    got = sampled_residual(fit, cap, 2, chunk=2)
    assert got.shape == (n, 19, 15)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("clipped", [False, True])
def test_sampled_valid_is_mask_and_no_saturated_channel(clipped):
    """The mask's interior (its rim left out, torchmetal.flakes.estimate.rim) and no saturated channel."""
    from types import SimpleNamespace

    from torchmetal.flakes.estimate.prescreen import sampled_valid
    from torchmetal.flakes.estimate.rim import interior

    g = torch.Generator().manual_seed(4)
    mask = torch.ones(1, 21, 18, dtype=torch.bool)
    mask[:, 15:, 12:] = False  # a corner cut out of the sample
    sat = (torch.rand(5, 3, 21, 18, generator=g) > 0.9) & clipped
    cap = SimpleNamespace(mask=mask, saturated=sat, num_shots=5)
    want = (interior(mask) & ~sat.any(1))[..., ::2, ::2]
    inner = interior(mask)[0]
    assert not bool(inner[14, 10]) and bool(inner[14, 8]) and bool(inner[12, 10])  # (14, 10) on the rim, (14, 8) not
    assert torch.equal(sampled_valid(cap, 2), want.expand(5, -1, -1))


@pytest.mark.parametrize("group", [1, 3, None])
def test_screen_in_shot_groups_equals_the_whole_screen(group):
    """screen_fit works a few shots at a time (bounded memory); every statistic is per shot, so the
    counts equal those of one pass over all shots rendered in the same groups (the render's rounding
    depends on its batch: ~2e-7)."""
    from tests.fit.helpers import replace, synth
    from torchmetal.fit.result import FitResult
    from torchmetal.flakes.estimate.prescreen import (
        SCREEN_STRIDE,
        residual_groups,
        sampled_residual,
        sampled_valid,
        screen_fit,
    )

    r = synth(size=64, shots=7, seed=2)
    t = r.truth
    fit = FitResult(texture=t["texture"], s=t["s"], alpha=t["alpha"], normals=r.capture.normals, size=r.capture.size)
    g = torch.Generator().manual_seed(5)
    img = r.capture.images.clone()
    for _ in range(60):  # glints
        k, i, j = int(torch.randint(7, (1,), generator=g)), *(int(v) for v in torch.randint(2, 60, (2,), generator=g))
        img[k, :, i : i + 2, j : j + 2] += 0.5
    mask = torch.ones_like(r.capture.mask)
    mask[:, :5] = False
    cap = replace(r.capture, images=img, mask=mask)
    groups = list(residual_groups(fit, cap, SCREEN_STRIDE, group))
    residual = torch.cat([r for _, r, _ in groups])
    core = torch.cat([c for _, _, c in groups])  # the highlight's peak (torchmetal.flakes.estimate.lobe_core): left out
    assert bool(core.any()) and torch.equal(residual, sampled_residual(fit, cap, SCREEN_STRIDE, chunk=group))
    want = glint_screen(residual, sampled_valid(cap, SCREEN_STRIDE) & ~core, pitch=SCREEN_STRIDE)
    got = screen_fit(fit, cap, shots_per_pass=group)
    assert got == want
    assert want[0] and max(want[1]["positive"]) > 0


def test_ring_max_is_the_maximum_on_the_square_ring():
    from torchmetal.flakes.estimate.prescreen import _ring_max

    z = torch.randn(2, 13, 17, generator=torch.Generator().manual_seed(5))
    r = 3
    got = _ring_max(z, r)
    for i in range(13):
        for j in range(17):
            ring = [z[:, a, b] for a in range(i - r, i + r + 1) for b in range(j - r, j + r + 1)
                    if 0 <= a < 13 and 0 <= b < 17 and max(abs(a - i), abs(b - j)) == r]
            want = torch.stack(ring).amax(0) if ring else torch.full((2,), -torch.inf)
            assert torch.equal(got[:, i, j], want), (i, j)


def test_bands_of_positive_misfit_are_not_glints():
    # thin bright streaks longer than a glint (a sheen, a highlight's streak) as often as spots would pass:
    # the screen counts spots only (a glint no longer than null_test.EXTENT)
    from torchmetal.flakes.estimate.null_test import EXTENT

    g, photo, phong, valid = _scene(6)
    bands = torch.zeros(N, 3, H, W)
    for k in range(N):
        for i in (20, 50, 80):
            j = int(torch.randint(4, W - 44, (1,), generator=g))
            bands[k, :, i, j : j + 40] = 0.5  # 40 px > EXTENT
    assert 40 > EXTENT
    passed, counts = _screen(photo + bands, phong, valid)
    assert not passed, counts
    assert _screen(photo + _spikes(g, 40, 0.5), phong, valid)[0]  # the same brightness as spots: glints
