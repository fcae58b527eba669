"""The pixel screen before the flake stage: noise and misfit fail it, glints pass it."""

import pytest
import torch

from torchmetal.flakes.prescreen import glint_screen

N, H, W = 8, 96, 96


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
    passed, counts = glint_screen(photo, phong, valid)
    assert not passed, counts
    assert counts["pixels"] == N * H * W
    assert glint_screen(photo, phong, valid, stride=2)[1]["pixels"] == N * (H // 2) * (W // 2)


def test_glints_pass_and_their_mirror_fails():
    g, photo, phong, valid = _scene(1)
    glints = _spikes(g, 40, 0.5)
    passed, counts = glint_screen(photo + glints, phong, valid)
    assert passed, counts
    assert counts["positive"][-1] >= 30  # bright: still counted at the top rung
    mirrored, counts = glint_screen(photo - glints, phong, valid)
    assert not mirrored, counts


def test_bright_glints_dig_no_negative_halo():
    g, photo, phong, valid = _scene(2)
    passed, counts = glint_screen(photo + _spikes(g, 30, 20.0, size=1), phong, valid)
    assert passed, counts
    assert counts["negative"][0] <= 3, counts


def test_smooth_misfit_is_not_a_glint():
    # a highlight of the wrong width: a wide bump of both signs, far above the noise
    _, photo, phong, valid = _scene(3)
    yy, xx = torch.meshgrid(torch.arange(H).float(), torch.arange(W).float(), indexing="ij")
    bump = torch.exp(-((yy - 48) ** 2 + (xx - 40) ** 2) / (2 * 10.0**2)) - torch.exp(-((yy - 48) ** 2 + (xx - 60) ** 2) / (2 * 6.0**2))
    passed, counts = glint_screen(photo + 0.5 * bump, phong, valid)
    assert not passed, counts


def test_masked_glints_do_not_count():
    g, photo, phong, valid = _scene(4)
    glints = _spikes(g, 40, 0.5)
    valid = valid & ~(glints > 0).any(1, keepdim=True)
    passed, counts = glint_screen(photo + glints, phong, valid)
    assert not passed, counts


@pytest.mark.parametrize("dtype", [torch.float16, torch.float64])
def test_dtypes_give_the_same_decision(dtype):
    g, photo, phong, valid = _scene(5)
    photo = photo + _spikes(g, 40, 0.5)
    passed, _ = glint_screen(photo.to(dtype), phong.to(dtype), valid)
    assert passed
