"""MD, the paper's Metallic Difference (torchmetal.flakes.model.md), and the anchors' toy check."""

import math

import pytest
import torch

from tests.flakes.scenes import make_scene
from torchmetal.errors import InputError
from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.model.field import flake_field, sparkle_render
from torchmetal.flakes.model.md import block_features, metallic_difference
from torchmetal.metrics import psnr

H = 256
NOISE = 0.004
# ~390 flakes on 256², ~20 % of them glint in one shot: enough for block statistics
BASE = {"density": 0.006, "area_log_mean": math.log(2.0), "tilt_sigma": 0.1, "glint_sigma": 0.05}


@pytest.fixture(scope="module")
def toy():
    """The anchors' toy check: reference photo and four candidate photos of the same sample.

    Reference: Phong + sparkles of a FlakeModel (seed 1) + noise. A: same statistics, new seed;
    B: no sparkle; C: 3× density; D: 3× flake radius (9× area). Candidates carry their own noise,
    i.e. they are other photos, not noise-free renders.
    """
    ref = make_scene(H, H, FlakeModel(**BASE, seed=1), shots=1, noise=NOISE, seed=0, quantize=False)
    gen = torch.Generator().manual_seed(5)

    def photo(sparkle):
        return (ref.phong + sparkle + NOISE * torch.randn(ref.phong.shape, generator=gen)).clamp(0, 1)[0]

    def sparkle(**kw):
        f = flake_field(FlakeModel(**(BASE | kw)), H, H, ref.normals)
        return sparkle_render(f, ref.normals, ref.lights, ref.intensities, ref.cameras, ref.size)

    parts = {
        "A": sparkle(seed=2),
        "B": torch.zeros_like(ref.phong),
        "C": sparkle(seed=2, density=3 * BASE["density"]),
        "D": sparkle(seed=2, area_log_mean=BASE["area_log_mean"] + math.log(9.0)),
    }
    cands = {k: photo(s) for k, s in parts.items()}
    clean = {k: (ref.phong + s)[0] for k, s in parts.items()}
    return ref, cands, clean


class TestMetallicDifference:
    def test_smoke(self, toy):
        ref, cands, _ = toy
        md = metallic_difference(ref.photos[0], cands["A"])
        assert isinstance(md, float) and 0.0 <= md <= 100.0

    def test_identical_is_zero(self, toy):
        ref, cands, _ = toy
        for x in (ref.photos[0], cands["C"], ref.phong[0]):
            assert metallic_difference(x, x.clone()) == 0.0

    def test_symmetric(self, toy):
        ref, cands, _ = toy
        for k in "ABCD":
            assert metallic_difference(ref.photos[0], cands[k]) == metallic_difference(cands[k], ref.photos[0])

    def test_range_and_sparkle_in_one_image_only(self, toy):
        ref, cands, _ = toy
        vals = [metallic_difference(ref.photos[0], cands[k], w) for k, w in (("A", 8), ("C", 32), ("D", 16))]
        assert all(0.0 <= v <= 100.0 for v in vals)
        # a noisy photo without sparkle has no pixel 5σ above its noise: MD = 100 exactly
        assert metallic_difference(ref.photos[0], cands["B"]) == 100.0

    def test_invariant_to_low_frequency_part(self, toy):
        # the 5×5 high-pass removes offsets and smooth shading: MD ≈ 0, far below a new seed's MD
        ref, cands, _ = toy
        x = ref.photos[0]
        yy, xx = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, H), indexing="ij")
        md_seed = metallic_difference(x, cands["A"])
        assert metallic_difference(x, x + 0.1) < 1e-3
        assert metallic_difference(x, x + 0.1 * xx - 0.05 * yy) < 1e-2
        assert metallic_difference(x, x + 0.2 * torch.sin(2 * math.pi * (2 * xx + yy))) < 0.2 < md_seed / 20
        # a different Phong under the same sparkles: the texture's low frequencies do not count
        other = ref.photos[0] - ref.phong[0] + 0.8 * ref.phong[0] + 0.05
        assert metallic_difference(x, other) < 1.0

    def test_scale_invariant(self, toy):
        ref, cands, _ = toy
        a, b = ref.photos[0], cands["A"]
        assert metallic_difference(2 * a, 2 * b) == pytest.approx(metallic_difference(a, b), abs=1e-4)

    def test_toy_check_md_ranks_and_psnr_fails(self, toy):
        """anchors.md: MD must rank "same statistics, new seed" first; PSNR does not."""
        ref, cands, _ = toy
        x = ref.photos[0]
        for window in (16, 32):
            md = {k: metallic_difference(x, cands[k], window) for k in "ABCD"}
            assert md["A"] < min(md["B"], md["C"], md["D"]), md
            assert md["A"] < 15.0 and min(md["B"], md["C"], md["D"]) > 2 * md["A"], md
        # measured (window 16): A 6.8, B 100, C 32.7, D 39.8
        p = {k: psnr(x, cands[k]) for k in "ABCD"}
        # PSNR prefers the sparkle-free image to a statistically perfect reconstruction
        assert p["B"] > p["A"], p  # measured: A 34.3 dB, B 36.3 dB, C 31.8 dB, D 27.1 dB

    def test_toy_check_noise_free_renders(self, toy):
        # noise-free photos and renders: the ranking holds; without a noise floor the Phong's own
        # high-pass counts as "sparkle" in both, so "no sparkle" reads < 100 (measured 73)
        ref, _, clean = toy
        x = (ref.phong + ref.sparkle)[0]
        md = {k: metallic_difference(x, clean[k]) for k in "ABCD"}
        assert md["A"] < min(md["B"], md["C"], md["D"]), md
        assert psnr(x, clean["B"]) > psnr(x, clean["A"])

    def test_shapes_and_batch(self, toy):
        ref, cands, _ = toy
        a, b, c = ref.photos[0, :, :96, :96], cands["A"][:, :96, :96], cands["C"][:, :96, :96]
        full = metallic_difference(a, b)
        assert metallic_difference(a[None], b[None]) == full
        gray = metallic_difference(a.mean(0), b.mean(0))
        assert metallic_difference(a.mean(0)[None], b.mean(0)[None]) == gray
        batch_a = torch.stack([a, a, c])
        batch_b = torch.stack([b, a, a])
        per = metallic_difference(batch_a, batch_b, reduction="none")
        assert per.shape == (3,)
        assert float(per[0]) == pytest.approx(full, abs=1e-4) and float(per[1]) == 0.0
        assert float(per[2]) == pytest.approx(metallic_difference(c, a), abs=1e-4)
        assert metallic_difference(batch_a, batch_b) == pytest.approx(float(per.mean()), abs=1e-4)

    def test_regions(self, toy):
        ref, cands, _ = toy
        for r in (1, 2, 4):
            assert 0.0 <= metallic_difference(ref.photos[0], cands["A"], regions=r) <= 100.0
        assert metallic_difference(ref.photos[0], ref.photos[0], regions=4) == 0.0

    def test_float64_close_to_float32(self, toy):
        ref, cands, _ = toy
        md32 = metallic_difference(ref.photos[0], cands["C"])
        md64 = metallic_difference(ref.photos[0].double(), cands["C"].double())
        assert md64 == pytest.approx(md32, abs=1e-3)

    def test_deterministic(self, toy):
        ref, cands, _ = toy
        assert metallic_difference(ref.photos[0], cands["D"]) == metallic_difference(ref.photos[0], cands["D"])


class TestMetallicDifferenceBadInput:
    def _raises(self, match, a, b, **kw):
        with pytest.raises(InputError, match=match) as err:
            metallic_difference(a, b, **kw)
        assert "\n" not in str(err.value) and "expected" in str(err.value)

    def test_errors(self):
        x = torch.rand(3, 32, 32)
        self._raises("img_a", x.numpy(), x)
        self._raises("img_b", x, torch.zeros(3, 32, 32, dtype=torch.int64))
        self._raises("img_b", x, torch.rand(3, 32, 31))
        self._raises("img_a", torch.rand(1, 1, 3, 32, 32), torch.rand(1, 1, 3, 32, 32))
        self._raises("img_a", torch.rand(32), torch.rand(32))
        bad = x.clone()
        bad[0, 1, 2] = float("nan")
        self._raises("NaN", bad, x)
        bad[0, 1, 2] = float("inf")
        self._raises("img_b", x, bad)
        self._raises("window", x, x, window=64)
        self._raises("window", x, x, window=1)
        self._raises("reduction", x, x, reduction="sum")
        self._raises("window", x, x, window=16.0)
        for k in (0.0, -1.0, float("nan"), float("inf")):
            self._raises("k", x, x, k=k)
        self._raises("regions", x, x, regions=0)


class TestBlockFeatures:
    def test_reference_values(self):
        # one 8×8 block with two sparkles above a threshold of 1
        x = torch.zeros(1, 1, 8, 8)
        x[0, 0, 2, 2] = 3.0
        x[0, 0, 5, 6] = 2.0
        x[0, 0, 5, 5] = 1.5  # above threshold but not a local maximum
        f = block_features(x, torch.ones(1, 1), 8)
        assert f.shape == (1, 1, 4, 1, 1)
        count, coverage, mean, peak = f[0, 0, :, 0, 0].tolist()
        assert count == 2.0
        assert coverage == pytest.approx(3 / 64)
        assert mean == pytest.approx((2.0 + 1.0 + 0.5) / 64)
        assert peak == 2.0

    def test_shape_drops_partial_blocks(self):
        f = block_features(torch.rand(2, 3, 20, 37), torch.full((2, 3), 0.5), 8)
        assert f.shape == (2, 3, 4, 2, 4)
