"""Connected components and region moments (torchmetal.flakes.estimate.regions) against OpenCV/SciPy/skimage."""

import math

import cv2
import numpy as np
import pytest
import scipy.ndimage as ndi
import torch
from skimage.draw import ellipse as draw_ellipse
from skimage.measure import label as sk_label
from skimage.measure import regionprops

from torchmetal.errors import InputError
from torchmetal.flakes.estimate import regions

BACKENDS = ["opencv", "kornia"]


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """True when two label images split the foreground into the same sets (labels may differ)."""
    if not np.array_equal(a > 0, b > 0):
        return False
    fg = a > 0
    pairs = np.unique(np.stack([a[fg], b[fg]]), axis=1)
    return pairs.shape[1] == len(np.unique(a[fg])) == len(np.unique(b[fg]))


def moments_of(mask: np.ndarray, weight: np.ndarray | None = None, dtype=torch.float64) -> dict:
    lab, n = regions.label_components(torch.from_numpy(mask.astype(bool))[None])
    px = regions.pixel_list(lab, n)
    if weight is None:
        w = torch.ones(px.ids.shape[0], dtype=dtype)
    else:
        w = torch.from_numpy(weight)[px.i, px.j].to(dtype)
    return regions.region_moments(px, w), lab[0].numpy()


def random_ellipses(h: int, w: int, cell: int, seed: int):
    """Non-touching random ellipses, one per cell (semi-axes 1.5–cell/2.6, any rotation)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.int32)
    k = 0
    for r0 in range(0, h - cell + 1, cell):
        for c0 in range(0, w - cell + 1, cell):
            a = rng.uniform(2.0, cell / 2.6)
            b = rng.uniform(1.5, a)
            rr, cc = draw_ellipse(r0 + cell / 2 + rng.uniform(-1, 1), c0 + cell / 2 + rng.uniform(-1, 1), b, a,
                                  rotation=rng.uniform(-math.pi, math.pi), shape=img.shape)
            k += 1
            img[rr, cc] = k
    return img


class TestLabelComponents:
    def test_smoke(self):
        mask = torch.zeros(1, 1, 5, 5, dtype=torch.bool)
        mask[0, 0, 1, 1] = mask[0, 0, 3, 3] = True
        lab, n = regions.label_components(mask)
        assert n == 2
        assert lab.shape == (1, 5, 5) and lab.dtype == torch.int64

    @pytest.mark.parametrize("backend", BACKENDS)
    def test_diagonal_is_connected(self, backend):
        # 8-connectivity: diagonal neighbours join; a knight's move does not
        mask = torch.zeros(1, 6, 6, dtype=torch.bool)
        mask[0, 0, 0] = mask[0, 1, 1] = mask[0, 2, 2] = True
        mask[0, 4, 3] = mask[0, 5, 5] = True
        lab, n = regions.label_components(mask, backend=backend)
        assert n == 3
        assert lab[0, 0, 0] == lab[0, 1, 1] == lab[0, 2, 2]
        assert lab[0, 4, 3] != lab[0, 5, 5]

    @pytest.mark.parametrize("backend", BACKENDS)
    @pytest.mark.parametrize("p", [0.3, 0.55, 0.75])
    def test_partition_matches_opencv_and_scipy(self, backend, p):
        gen = torch.Generator().manual_seed(int(p * 100))
        mask = torch.rand(3, 1, 37, 53, generator=gen) < p
        lab, n = regions.label_components(mask, backend=backend)
        total = 0
        for b in range(3):
            m = mask[b, 0].numpy().astype(np.uint8)
            n_cv, lab_cv = cv2.connectedComponents(m, connectivity=8)
            lab_sp, n_sp = ndi.label(m, structure=np.ones((3, 3)))
            assert n_cv - 1 == n_sp
            assert same_partition(lab[b].numpy(), lab_cv)
            assert same_partition(lab[b].numpy(), lab_sp)
            total += n_sp
        assert n == total

    @pytest.mark.parametrize("backend", BACKENDS)
    def test_labels_consecutive_in_batch_order(self, backend):
        gen = torch.Generator().manual_seed(3)
        mask = torch.rand(4, 1, 20, 20, generator=gen) < 0.4
        mask[2] = False  # an empty image in the middle
        lab, n = regions.label_components(mask, backend=backend)
        used = torch.unique(lab[lab > 0])
        assert torch.equal(used, torch.arange(1, n + 1))
        assert not bool((lab[2] > 0).any())
        hi = 0
        for b in range(4):
            if bool((lab[b] > 0).any()):
                assert int(lab[b][lab[b] > 0].min()) == hi + 1
                hi = int(lab[b].max())

    @pytest.mark.parametrize("backend", BACKENDS)
    def test_backends_agree(self, backend):
        gen = torch.Generator().manual_seed(5)
        mask = torch.rand(2, 64, 48, generator=gen) < 0.5
        a, na = regions.label_components(mask, backend="opencv")
        b, nb = regions.label_components(mask, backend=backend)
        assert na == nb
        for k in range(2):
            assert same_partition(a[k].numpy(), b[k].numpy())

    @pytest.mark.parametrize("backend", BACKENDS)
    @pytest.mark.parametrize("shape", [(1, 1, 1, 1), (2, 1, 1, 1), (1, 1, 1, 7), (1, 1, 7, 1)])
    def test_tiny_images(self, backend, shape):
        for value, expect in ((False, 0), (True, shape[0])):
            lab, n = regions.label_components(torch.full(shape, value), backend=backend)
            assert n == expect
            assert lab.shape == (shape[0],) + shape[-2:]
            if value:
                assert torch.equal(lab.reshape(shape[0], -1)[:, 0], torch.arange(1, shape[0] + 1))

    @pytest.mark.parametrize("backend", BACKENDS)
    def test_empty_mask(self, backend):
        lab, n = regions.label_components(torch.zeros(2, 1, 9, 11, dtype=torch.bool), backend=backend)
        assert n == 0 and lab.shape == (2, 9, 11) and int(lab.abs().sum()) == 0

    def test_nonzero_is_foreground(self):
        m = torch.tensor([[[0.0, 0.5, 0.0, 2.0]]])
        lab, n = regions.label_components(m)
        assert n == 2 and lab[0, 0].tolist() == [0, 1, 0, 2]

    def test_bad_backend(self):
        with pytest.raises(InputError, match="backend"):
            regions.label_components(torch.ones(1, 2, 2, dtype=torch.bool), backend="scipy")

    def test_deterministic(self):
        gen = torch.Generator().manual_seed(8)
        mask = torch.rand(2, 1, 31, 31, generator=gen) < 0.5
        for backend in BACKENDS:
            a = regions.label_components(mask, backend=backend)
            b = regions.label_components(mask, backend=backend)
            assert a[1] == b[1] and torch.equal(a[0], b[0])


class TestRegionMoments:
    def test_smoke_single_pixel(self):
        m, _ = moments_of(np.array([[0, 0], [0, 1]]))
        assert m["area"].tolist() == [1.0]
        assert m["cy"].tolist() == [1.5] and m["cx"].tolist() == [1.5]  # pixel-centre coordinates
        assert m["major"].tolist() == [0.0] and m["minor"].tolist() == [0.0]

    def test_one_by_one_image(self):
        m, _ = moments_of(np.ones((1, 1)))
        assert m["area"].tolist() == [1.0] and m["cy"].tolist() == [0.5] and m["cx"].tolist() == [0.5]
        assert all(torch.isfinite(v).all() for v in m.values())

    def test_shapes_and_dtypes(self):
        img = random_ellipses(48, 48, 16, seed=0)
        for dtype in (torch.float32, torch.float64):
            m, _ = moments_of(img > 0, dtype=dtype)
            assert set(m) == {"area", "cy", "cx", "mu_yy", "mu_xx", "mu_xy", "major", "minor", "angle"}
            for v in m.values():
                assert v.shape == (9,) and v.dtype == dtype

    def test_empty(self):
        px = regions.pixel_list(torch.zeros(1, 4, 4, dtype=torch.int64), 0)
        m = regions.region_moments(px, torch.zeros(0))
        for v in m.values():
            assert v.shape == (0,)

    def test_against_skimage_regionprops(self):
        img = random_ellipses(160, 160, 20, seed=1)
        m, _ = moments_of(img > 0)
        props = regionprops(sk_label(img > 0, connectivity=2))
        assert len(props) == len(m["area"]) == 64
        # match components by position (label numbering is an implementation detail)
        ours = np.stack([m["cy"].numpy() - 0.5, m["cx"].numpy() - 0.5], 1)
        tested_angles = 0
        for p in props:
            k = int(np.argmin(((ours - np.array(p.centroid)) ** 2).sum(1)))
            assert float(m["area"][k]) == p.area
            np.testing.assert_allclose(ours[k], p.centroid, atol=1e-10)
            np.testing.assert_allclose(float(m["major"][k]), p.axis_major_length, rtol=1e-10, atol=1e-10)
            np.testing.assert_allclose(float(m["minor"][k]), p.axis_minor_length, rtol=1e-10, atol=1e-10)
            angle = float(m["angle"][k])
            assert -math.pi / 2 < angle <= math.pi / 2
            if p.axis_minor_length < 0.9 * p.axis_major_length:  # angle ill-defined for discs
                # skimage: from the row axis, counter-clockwise; ours: from +col towards up
                d = (angle - (p.orientation - math.pi / 2) + math.pi / 2) % math.pi - math.pi / 2
                assert abs(d) < 1e-9
                tested_angles += 1
        assert tested_angles > 30

    @pytest.mark.parametrize("rotation", [0.0, 0.4, 1.2, -0.7])
    def test_angle_convention(self, rotation):
        # skimage.draw rotates counter-clockwise as displayed (rows down), i.e. towards image up
        img = np.zeros((64, 64), bool)
        rr, cc = draw_ellipse(32, 32, 5, 14, rotation=rotation, shape=img.shape)
        img[rr, cc] = True
        m, _ = moments_of(img)
        d = (float(m["angle"][0]) - rotation + math.pi / 2) % math.pi - math.pi / 2
        assert abs(d) < 0.02

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_vertical_axis_is_plus_half_pi(self, dtype):
        # mu_xy is exactly ±0 for an axis-aligned region; atan2(−0, x<0) = −π must not leak out
        img = np.zeros((12, 12), bool)
        img[2:10, 5:7] = True
        m, _ = moments_of(img, dtype=dtype)
        assert float(m["angle"][0]) == pytest.approx(math.pi / 2, abs=1e-6)
        m, _ = moments_of(img.T.copy(), dtype=dtype)
        assert float(m["angle"][0]) == 0.0

    def test_weighted_centroid_against_skimage(self):
        img = random_ellipses(80, 80, 20, seed=2)
        rng = np.random.default_rng(2)
        weight = rng.uniform(0.1, 2.0, img.shape)
        m, _ = moments_of(img > 0, weight)
        props = regionprops(sk_label(img > 0, connectivity=2), intensity_image=weight)
        ours = np.stack([m["cy"].numpy() - 0.5, m["cx"].numpy() - 0.5], 1)
        for p in props:
            dist = ((ours - np.array(p.centroid_weighted)) ** 2).sum(1)
            assert dist.min() < 1e-18

    def test_weighted_moments_reference(self):
        # two pixels on a row, weights 1 and 3: centroid at 3/4, variance 3/16 along columns
        px = regions.PixelList(torch.tensor([0, 0]), torch.tensor([0, 0]), torch.tensor([2, 2]), torch.tensor([4, 5]), 1)
        m = regions.region_moments(px, torch.tensor([1.0, 3.0], dtype=torch.float64))
        assert float(m["cy"][0]) == 2.5
        assert float(m["cx"][0]) == pytest.approx(5.25, abs=1e-12)
        assert float(m["mu_xx"][0]) == pytest.approx(3 / 16, abs=1e-12)
        assert float(m["mu_yy"][0]) == 0.0 and float(m["mu_xy"][0]) == 0.0
        assert float(m["major"][0]) == pytest.approx(4 * math.sqrt(3 / 16), abs=1e-12)
        assert float(m["angle"][0]) == 0.0

    def test_zero_and_negative_weights(self):
        # weights are clamped at 0; an all-zero component falls back to uniform weights
        px = regions.PixelList(torch.tensor([0, 0, 1, 1]), torch.zeros(4, dtype=torch.int64),
                               torch.tensor([0, 0, 5, 5]), torch.tensor([0, 1, 0, 3]), 2)
        m = regions.region_moments(px, torch.tensor([0.0, 0.0, -1.0, 2.0], dtype=torch.float64))
        assert m["cx"].tolist() == [1.0, 3.5]
        assert m["area"].tolist() == [2.0, 2.0]
        assert all(bool(torch.isfinite(v).all()) for v in m.values())

    def test_float32_close_to_float64(self):
        img = random_ellipses(60, 60, 20, seed=4)
        m32, _ = moments_of(img > 0, dtype=torch.float32)
        m64, _ = moments_of(img > 0, dtype=torch.float64)
        for key in ("cy", "cx", "major", "minor"):
            torch.testing.assert_close(m32[key].double(), m64[key], rtol=1e-5, atol=1e-4)

    def test_deterministic(self):
        img = random_ellipses(60, 60, 20, seed=5)
        a, _ = moments_of(img > 0)
        b, _ = moments_of(img > 0)
        for key in a:
            assert torch.equal(a[key], b[key])


class TestSegmentOps:
    def test_sum_max_argmax(self):
        ids = torch.tensor([0, 1, 0, 2, 1])
        v = torch.tensor([1.0, 5.0, 3.0, -2.0, 4.0])
        assert regions.segment_sum(ids, v, 4).tolist() == [4.0, 9.0, -2.0, 0.0]
        mx = regions.segment_max(ids, v, 4)
        assert mx[:3].tolist() == [3.0, 5.0, -2.0] and mx[3] == float("-inf")
        assert regions.segment_argmax(ids, v, 3).tolist() == [2, 1, 3]

    def test_argmax_ties_take_the_first(self):
        ids = torch.zeros(100_000, dtype=torch.int64)
        ids[50_000:] = 1
        v = torch.ones(100_000)  # every row ties: the first of each component, every time
        for _ in range(3):
            assert regions.segment_argmax(ids, v, 2).tolist() == [0, 50_000]

    def test_patches_fill_outside(self):
        x = torch.arange(16.0).view(1, 1, 4, 4)
        p = regions.patches(x, torch.tensor([0]), torch.tensor([0]), torch.tensor([3]), 1, fill=-1.0)
        assert p.shape == (1, 1, 3, 3)
        assert p[0, 0].tolist() == [[-1.0, -1.0, -1.0], [2.0, 3.0, -1.0], [6.0, 7.0, -1.0]]
