"""torchmetal.metrics: PSNR / MSE reference values, masks, sRGB space, clipping, errors, sparkle count."""

import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchmetal.errors import InputError
from torchmetal.metrics import chroma_artifact_share, md, mse, psnr, sparkle_count, srgb_encode


def _srgb_by_hand(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


class TestPSNR:
    def test_reference_values(self):
        ref = torch.rand(2, 3, 8, 8, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.8
        pred = ref + 0.1  # constant error 0.1 inside [0, 1]: MSE 0.01
        assert mse(pred, ref) == pytest.approx(0.01, rel=1e-12)
        assert psnr(pred, ref) == pytest.approx(20.0, abs=1e-9)
        assert psnr(pred, ref, peak=10.0) == pytest.approx(40.0, abs=1e-9)
        assert psnr(ref - 0.01 * (ref > 0.5), ref) == pytest.approx(  # only part of the pixels err
            10 * math.log10(1 / (1e-4 * float((ref > 0.5).double().mean()))), abs=1e-6)
        # the peak is 1, not ref.max(): a dim image does not score worse for being dim
        assert psnr(0.1 * pred, 0.1 * ref) == pytest.approx(40.0, abs=1e-9)

    def test_identical_is_inf(self):
        x = torch.rand(3, 5, 5)
        assert psnr(x, x) == math.inf
        assert psnr(x.numpy(), x.numpy(), space="srgb") == math.inf
        assert mse(x, x) == 0.0

    def test_layouts_and_float64(self):
        g = torch.Generator().manual_seed(1)
        ref = torch.rand(3, 16, 16, generator=g)
        pred = (ref + 0.05 * torch.randn(3, 16, 16, generator=g)).float()
        chw = psnr(pred, ref)
        assert psnr(pred.permute(1, 2, 0), ref.permute(1, 2, 0)) == pytest.approx(chw, abs=1e-12)
        assert psnr(pred[None], ref[None]) == pytest.approx(chw, abs=1e-12)
        # float64 accumulation: the float32 inputs give the float64 answer
        assert psnr(pred, ref) == pytest.approx(psnr(pred.double(), ref.double()), abs=1e-12)

    def test_numpy_and_torch_identical(self):
        g = torch.Generator().manual_seed(2)
        ref = torch.rand(2, 3, 12, 10, generator=g)
        pred = ref + 0.2 * torch.randn(2, 3, 12, 10, generator=g)  # goes outside [0, 1]: clipping matters
        mask = torch.rand(2, 1, 12, 10, generator=g) > 0.3
        for kw in ({}, {"mask": mask}, {"space": "srgb"}, {"clip": False}, {"peak": 0.5, "mask": mask}):
            npkw = {k: (v.numpy() if isinstance(v, torch.Tensor) else v) for k, v in kw.items()}
            assert psnr(pred.numpy(), ref.numpy(), **npkw) == psnr(pred, ref, **kw)
            assert psnr(pred.numpy(), ref, **kw) == psnr(pred, ref, **kw)  # mixed is fine too
        assert mse(pred.numpy(), ref.numpy(), mask=mask.numpy()) == mse(pred, ref, mask=mask)

    def test_mask_ignores_masked_out_errors(self):
        ref = torch.full((2, 3, 4, 4), 0.5, dtype=torch.float64)
        pred = ref + 0.01
        pred[1, :, 0, 0] = 100.0  # a huge outlier (and NaN elsewhere): masked out
        pred[0, 2, 3, 3] = float("nan")
        hw = torch.ones(4, 4, dtype=torch.bool)
        hw[0, 0] = hw[3, 3] = False
        for m in (hw, hw[None, None], hw[None, None].expand(2, 1, 4, 4), hw.expand(2, 3, 4, 4), hw.numpy(),
                  hw.int(), hw.double().numpy()):
            assert psnr(pred, ref, mask=m) == pytest.approx(40.0, abs=1e-9)
        assert psnr(pred.permute(0, 2, 3, 1), ref.permute(0, 2, 3, 1), mask=hw) == pytest.approx(40.0, abs=1e-9)
        # a mask broadcast over channels counts all channels of its pixels
        ref2 = torch.zeros(3, 2, 2, dtype=torch.float64)
        pred2 = ref2.clone()
        pred2[0, 0, 0] = 0.3  # one wrong channel of pixel (0, 0)
        only = torch.tensor([[True, False], [False, False]])
        assert mse(pred2, ref2, mask=only) == pytest.approx(0.09 / 3, rel=1e-12)
        assert mse(pred2, ref2, mask=only.expand(3, 2, 2) & (torch.arange(3) == 0)[:, None, None]) == pytest.approx(0.09)

    def test_srgb_space_by_hand(self):
        g = torch.Generator().manual_seed(3)
        ref = torch.rand(3, 9, 9, generator=g, dtype=torch.float64) * 1.2 - 0.1
        pred = ref + 0.05 * torch.randn(3, 9, 9, generator=g, dtype=torch.float64)
        e = np.mean((_srgb_by_hand(pred.numpy()) - _srgb_by_hand(ref.numpy())) ** 2)
        want = 10 * math.log10(1 / e)
        assert psnr(pred, ref, space="srgb") == pytest.approx(want, abs=1e-9)
        assert psnr(pred, ref, space="srgb", clip=False) == pytest.approx(want, abs=1e-9)  # srgb always clips
        assert psnr(pred, ref, space="srgb") != pytest.approx(psnr(pred, ref), abs=0.1)

    def test_srgb_encode(self):
        x = np.array([0.0, 0.002, 0.0031308, 0.01, 0.18, 0.5, 1.0])
        want = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
        out = srgb_encode(x)
        assert isinstance(out, np.ndarray) and out.dtype == np.float64
        np.testing.assert_allclose(out, want, rtol=0, atol=1e-12)
        assert srgb_encode(x.astype(np.float32)).dtype == np.float32
        t = srgb_encode(torch.from_numpy(x))
        assert isinstance(t, torch.Tensor) and t.dtype == torch.float64
        np.testing.assert_allclose(t.numpy(), want, rtol=0, atol=1e-12)
        assert float(srgb_encode(torch.tensor(0.5))) == pytest.approx(0.735356983, abs=1e-6)

    def test_clip(self):
        ref = torch.full((3, 4, 4), 0.9, dtype=torch.float64)
        pred = torch.full((3, 4, 4), 1.4, dtype=torch.float64)  # 0.5 over, 0.1 over after clipping
        assert psnr(pred, ref) == pytest.approx(20.0, abs=1e-9)
        assert psnr(pred, ref, clip=False) == pytest.approx(10 * math.log10(1 / 0.25), abs=1e-9)
        assert mse(pred, ref) == pytest.approx(0.01) and mse(pred, ref, clip=False) == pytest.approx(0.25)
        # both saturated (above 1) or both negative: equal after clipping
        assert psnr(ref + 1.0, ref + 2.0) == math.inf and psnr(-ref, -2 * ref) == math.inf
        # non-finite values are rejected before clipping (an Inf must not turn into a clean 1)
        with pytest.raises(InputError, match="non-finite"):
            psnr(torch.full((2, 2), math.inf), torch.ones(2, 2))

    def test_errors(self):
        with pytest.raises(InputError, match=r"shape \(3, 4, 4\).*\(3, 4, 5\)"):
            psnr(torch.zeros(3, 4, 4), torch.zeros(3, 4, 5))
        with pytest.raises(InputError, match="shape"):
            mse(np.zeros((4, 4, 3)), np.zeros((3, 4, 4)))
        with pytest.raises(InputError, match="selects none"):
            psnr(torch.zeros(3, 2, 2), torch.ones(3, 2, 2), mask=torch.zeros(2, 2, dtype=torch.bool))
        with pytest.raises(InputError, match="non-finite"):
            psnr(torch.tensor([0.1, float("nan")]), torch.zeros(2))
        with pytest.raises(InputError, match="non-finite"):
            mse(torch.zeros(2), np.array([0.0, np.nan]), mask=np.array([False, True]))
        with pytest.raises(InputError, match="broadcastable"):
            psnr(torch.zeros(3, 4, 4), torch.zeros(3, 4, 4), mask=torch.ones(5, 4, dtype=torch.bool))
        with pytest.raises(InputError, match="0/1"):
            psnr(torch.zeros(3, 4, 4), torch.zeros(3, 4, 4), mask=torch.full((4, 4), 0.5))
        with pytest.raises(InputError, match="peak"):
            psnr(torch.zeros(2), torch.ones(2), peak=0.0)
        with pytest.raises(InputError, match="space"):
            psnr(torch.zeros(2), torch.ones(2), space="log")
        with pytest.raises(ValueError):  # InputError is a ValueError: old `except ValueError` still works
            psnr(torch.zeros(2), torch.zeros(3))
        try:
            psnr(torch.zeros(2), torch.zeros(3))
        except InputError as e:
            assert "\n" not in str(e)

    def test_report_and_bench_use_it(self):
        import torchmetal.report as report

        assert report.psnr is psnr

    def test_import_is_cheap(self):
        """No heavy package, and of the flakes only the render model (MD lives there; no estimation, no renderer)."""
        code = ("import sys, torchmetal.metrics; "
                "print(' '.join(m for m in ('kornia', 'onnx', 'onnxruntime', 'matplotlib', 'cv2', 'scipy', "
                "'torchmetal.flakes.estimate', 'torchmetal.flakes.stage', 'torchmetal.renderer') "
                "if m in sys.modules))")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        assert out.stdout.strip() == ""


def test_md_wrapper():
    from torchmetal.flakes.model.md import metallic_difference

    g = torch.Generator().manual_seed(4)
    a = torch.rand(3, 32, 32, generator=g) * 0.1
    b = a.clone()
    b[:, ::7, ::5] += 0.8  # sparkles in b only
    assert md(a, b) == metallic_difference(a, b)
    assert md(a, b, 16, k=4.0, regions=2) == metallic_difference(a, b, 16, k=4.0, regions=2)
    assert md(a, a) == 0.0 and md(a, b) > 50.0


class TestSparkleCount:
    @staticmethod
    def _noise(h=96, w=80, seed=0, sigma=0.01):
        g = torch.Generator().manual_seed(seed)
        return sigma * torch.randn(3, h, w, generator=g)

    def test_three_blobs(self):
        res = self._noise()
        res[:, 10:13, 10:14] += 0.2  # a 3×4 blob, all channels
        res[1, 50, 60] += 0.3  # a single bright pixel in one channel
        res[0, 70:75, 20:22] += 0.15
        res[2, 74:76, 22:24] += 0.15  # touches the previous one diagonally/by side: still one blob
        res[0, 30, 40] -= 0.5  # dark: not a sparkle
        assert sparkle_count(res) == 3
        assert sparkle_count(res.permute(1, 2, 0)) == 3  # (H, W, 3)
        assert sparkle_count(res.numpy()) == 3 and sparkle_count(res.permute(1, 2, 0).numpy()) == 3
        # 8-connectivity: two diagonal neighbours are one blob
        diag = self._noise(seed=1)
        diag[:, 5, 5] += 0.3
        diag[:, 6, 6] += 0.3
        assert sparkle_count(diag) == 1

    def test_pure_noise_is_zero(self):
        for seed in range(3):
            assert sparkle_count(self._noise(256, 256, seed=seed)) == 0
        assert sparkle_count(torch.zeros(3, 8, 8)) == 0

    def test_k_and_mask(self):
        res = self._noise(seed=5)  # σ 0.01
        res[:, 10, 10] += 0.2
        res[:, 40, 40] += 0.1  # 10 σ
        res[:, 80, 70] += 0.2
        assert sparkle_count(res) == 3
        assert sparkle_count(res, k=15.0) == 2
        m = torch.ones(96, 80, dtype=torch.bool)
        m[70:, :] = False
        assert sparkle_count(res, mask=m) == 2
        assert sparkle_count(res, mask=m[None].numpy()) == 2
        assert sparkle_count(res, mask=m[..., None]) == 2
        # masked-out garbage neither counts nor breaks the noise estimate
        res[:, 90, 5] = float("nan")
        assert sparkle_count(res, mask=m) == 2

    def test_errors(self):
        with pytest.raises(InputError, match=r"residual \(3, H, W\) or \(H, W, 3\), found \(4, 5, 6\)"):
            sparkle_count(torch.zeros(4, 5, 6))
        with pytest.raises(InputError, match="mask"):
            sparkle_count(torch.zeros(3, 5, 6), mask=torch.ones(6, 5, dtype=torch.bool))
        with pytest.raises(InputError, match="selects none"):
            sparkle_count(torch.zeros(3, 5, 6), mask=torch.zeros(5, 6, dtype=torch.bool))
        with pytest.raises(InputError, match="non-finite"):
            sparkle_count(torch.full((3, 5, 6), float("nan")))
        with pytest.raises(InputError, match="k"):
            sparkle_count(torch.zeros(3, 5, 6), k=0)


class TestChromaArtifactShare:
    def test_counts_blocks_whose_colour_differs_not_their_brightness(self):
        grey = torch.full((3, 32, 32), 0.2, dtype=torch.float64)
        assert chroma_artifact_share(grey, grey) == 0.0
        assert chroma_artifact_share(grey * 3.0, grey) == 0.0  # brighter, same hue: no chroma distance
        gold = grey.clone()
        gold[:, :8, :16] = torch.tensor([0.6, 0.4, 0.05], dtype=torch.float64).view(3, 1, 1)  # 2 of 16 blocks
        assert chroma_artifact_share(gold, grey) == pytest.approx(2 / 16)
        slight = grey.clone()
        slight[0] *= 1.02  # a tint well below ΔC 15
        assert chroma_artifact_share(slight, grey) == 0.0

    def test_block_means_mask_and_partial_edges(self):
        g = torch.Generator().manual_seed(0)
        ref = torch.full((1, 3, 20, 16), 0.3, dtype=torch.float64)
        noisy = ref + 0.1 * (torch.rand(ref.shape, generator=g, dtype=torch.float64) - 0.5)  # averages out per block
        assert chroma_artifact_share(noisy, ref) == 0.0  # 2×2 whole blocks; the 4 edge rows are left out
        pred = ref.clone()
        pred[:, 1, :8, :8] = 0.05  # a magenta block
        mask = torch.ones(20, 16, dtype=torch.bool)
        assert chroma_artifact_share(pred, ref) == pytest.approx(0.25)
        mask[0, 0] = False  # the block is no longer wholly inside
        assert chroma_artifact_share(pred, ref, mask=mask) == 0.0
        assert math.isnan(chroma_artifact_share(torch.zeros(3, 4, 4), torch.zeros(3, 4, 4)))
