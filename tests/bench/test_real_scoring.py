"""The real section's scoring helpers (torchmetal.bench.scoring): box-averaged PSNR at several scales, the
extrapolation share, and the per-capture table (torchmetal.bench.runner.real_scales_table) on tiny synthetic
captures."""

import math

import pytest
import torch

from torchmetal.bench.runner import real_scales_table
from torchmetal.bench.scoring import box_average, extrapolation_share, psnr_scales
from torchmetal.errors import InputError


def test_box_average_uses_only_valid_pixels_and_drops_mostly_invalid_blocks():
    x = torch.full((3, 8, 8), 0.25)
    x[:, 0, 0] = 100.0  # a saturated pixel: invalid, must not leak into its block
    valid = torch.ones(3, 8, 8, dtype=torch.bool)
    valid[:, 0, 0] = False
    valid[:, 4:, 4:] = False  # one whole block invalid
    valid[:, 4:6, :4] = False  # half of another block invalid: still kept
    mean, keep = box_average(x, valid, 4)
    assert mean.shape == (3, 2, 2) and keep.shape == (3, 2, 2)
    assert torch.allclose(mean[keep], torch.full_like(mean[keep], 0.25))
    assert keep[:, 0, 0].all() and keep[:, 1, 0].all() and not keep[:, 1, 1].any()
    same, k1 = box_average(x, valid, 1)
    assert torch.equal(same, x.double()) and torch.equal(k1, valid)


def test_psnr_scales_averages_fine_noise_away_but_keeps_a_broad_error():
    g = torch.Generator().manual_seed(0)
    photo = 0.2 + 0.6 * torch.rand(3, 64, 64, generator=g)
    checker = ((torch.arange(64)[:, None] + torch.arange(64)[None]) % 2 * 2 - 1).double()  # ±1, zero mean per 4×4
    fine = photo.double() + 0.05 * checker
    s = psnr_scales(fine, photo, None)
    assert set(s) == {"1", "4", "16"}
    assert 15 < s["1"] < 40 and s["4"] > s["1"] + 15 and s["16"] > s["1"] + 15  # the checker averages out
    broad = photo.clone()
    broad[:, :32] *= 1.5  # half the image a stop-ish too bright: every scale sees it
    b = psnr_scales(broad, photo, None)
    assert b["16"] == pytest.approx(b["1"], abs=2.0) and b["1"] < 25
    # invalid (saturated) pixels do not count at any scale
    bad = photo.clone()
    bad[:, :8, :8] = 0.0
    valid = torch.ones(3, 64, 64, dtype=torch.bool)
    valid[:, :8, :8] = False
    assert all(math.isinf(v) for v in psnr_scales(bad, photo, valid).values())


def test_extrapolation_share_counts_blocks_no_fitted_photo_reached():
    base = torch.full((3, 64, 64), 0.1)
    fitted = base.repeat(3, 1, 1, 1)
    fitted[0, :, :32, :32] = 0.8  # a highlight seen in the top-left quarter by a fitted shot
    photo = base.clone()
    photo[:, :32, :32] = 0.5  # the left-out shot's highlight there: seen brighter before
    photo[:, 32:, 32:] = 0.5  # and in the bottom-right quarter: never seen
    assert extrapolation_share(photo, fitted, block=16) == pytest.approx(0.25)
    assert extrapolation_share(fitted[0], fitted[1:], block=16) == pytest.approx(0.25)
    assert extrapolation_share(base, fitted, block=16) == 0.0
    mask = torch.zeros(64, 64, dtype=torch.bool)
    mask[32:] = True  # only the bottom half: half of its blocks are the unseen highlight
    assert extrapolation_share(photo, fitted, mask=mask, block=16) == pytest.approx(0.5)
    with pytest.raises(InputError):
        extrapolation_share(photo, fitted[0], block=16)


def test_real_scales_table_has_one_row_per_variant_and_score_kind():
    kind = lambda a, e: {"psnr": {"1": a, "4": a + 1, "16": a + 2}, "chroma": 0.05, "extrapolation": e}  # noqa: E731
    r = {"name": "cap", "size": [64, 64], "shots": 4,
         "default": {"scores": {"in_sample": kind(20.0, None), "light_fitted": kind(19.0, 0.1), "left_out": kind(18.0, 0.1)}},
         "global": {"scores": {"in_sample": kind(17.0, None), "left_out": kind(16.0, 0.1)}}}
    text = real_scales_table(r, ["default", "global", "paper"])
    lines = [ln.rstrip(" |") for ln in text.splitlines() if ln.startswith("| ")][1:]
    assert len(lines) == 5
    assert lines[0].split(" | ")[1:7] == ["own shots", "20.00", "21.00", "22.00", "5.0%", "–"]
    assert lines[2].split(" | ")[1:7] == ["left out, as captured", "18.00", "19.00", "20.00", "5.0%", "10.0%"]
    assert "cap" in text and "64×64" in text


def test_extrapolation_share_of_an_image_smaller_than_a_block_is_nan():
    import math

    import torch

    from torchmetal.bench.scoring import extrapolation_share

    photo = torch.rand(3, 28, 28)
    assert math.isnan(extrapolation_share(photo, torch.rand(2, 3, 28, 28)))  # the quick plan's sphere is 28 px
