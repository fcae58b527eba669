"""The fit report's disagreement map and registration (torchmetal.report.disagreement, .registration,
.fit_maps) on tiny synthetic captures: quiet where the shots agree with the model, lit where an edge moves
between shots; a shot moved by a known shift is measured."""

import numpy as np
import pytest
import torch

from torchmetal.registration import shot_shifts
from torchmetal.report.disagreement import disagreement_map, disagreement_png


def _texture(h=128, w=128, seed=0):
    g = torch.Generator().manual_seed(seed)
    t = torch.nn.functional.avg_pool2d(torch.rand(1, 3, h + 2, w + 2, generator=g), 3, stride=1)[0]
    return 0.05 + 0.4 * t


def test_flat_capture_whose_shots_agree_with_the_model_stays_near_zero():
    g = torch.Generator().manual_seed(1)
    tex = _texture()
    shade = torch.linspace(0.6, 1.4, 7).reshape(7, 1, 1, 1) * torch.linspace(0.8, 1.2, 128).reshape(1, 1, 1, 128)
    render = tex * shade
    photos = render + 0.004 * torch.randn(render.shape, generator=g) * render.sqrt()  # shot noise-like
    marked, s = disagreement_map(photos, render)
    assert marked.shape == (128, 128) and s["assessed"] == 1.0
    assert s["share"] < 0.002, s
    # an exposure misfit of one shot and a highlight the model misses in another do not light it up either
    photos[2] *= 1.25
    photos[4, :, 40:60, 40:60] += 0.5
    _, s2 = disagreement_map(photos, render)
    assert s2["share"] < 0.005, s2


def test_an_edge_that_moves_between_shots_lights_up_and_nothing_else():
    n, h, w = 7, 128, 128
    g = torch.Generator().manual_seed(2)
    photos = torch.empty(n, 3, h, w)
    for k in range(n):  # a dark tile whose left edge sits at x = 60 + 2k (parallax): 12 px in all
        img = torch.full((3, h, w), 0.4)
        img[:, :, 60 + 2 * k :] = 0.05
        photos[k] = img + 0.005 * img.sqrt() * torch.randn(3, h, w, generator=g)  # shot noise-like
    render = photos.mean(0, keepdim=True).expand(n, -1, -1, -1).clone()  # the best single texture: a ramp
    marked, s = disagreement_map(photos, render)
    cols = marked.float().mean(0)
    assert cols[62:72].mean() > 0.5, cols  # the band the edge sweeps through
    assert cols[:50].sum() == 0 and cols[82:].sum() == 0
    assert 0.02 < s["share"] < 0.15, s
    # an invalid observation is left out: a pixel seen valid by fewer than 3 shots is not assessed
    valid = torch.ones(n, 3, h, w, dtype=torch.bool)
    valid[:5, :, :10] = False
    m2, s2 = disagreement_map(photos, render, valid)
    assert not m2[:, :10].any() and s2["assessed"] == pytest.approx(1 - 10 / w)


def test_disagreement_png_marks_red_over_the_photo(tmp_path):
    import cv2

    marked = torch.zeros(16, 24, dtype=torch.bool)
    marked[4:8, 5:9] = True
    p = disagreement_png(tmp_path / "d.png", marked, torch.full((3, 16, 24), 0.2))
    img = cv2.imread(str(p))[..., ::-1]
    assert img.shape == (16, 24, 3)
    assert (img[4:8, 5:9] == [255, 0, 0]).all() and (img[0, 0, 0] == img[0, 0, 1] == img[0, 0, 2])


def test_registration_measures_a_shot_moved_by_a_known_shift():
    import cv2

    g = torch.Generator().manual_seed(3)
    tex = cv2.GaussianBlur((0.1 + 0.4 * torch.rand(192, 192, 3, generator=g)).numpy(), (0, 0), 2.0)
    shots = []
    for k in range(5):
        dx, dy = (2.5, -1.5) if k == 3 else (0.0, 0.0)
        m = np.float32([[1, 0, dx], [0, 1, dy]])
        shifted = cv2.warpAffine(tex, m, (192, 192), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        shade = 0.6 + 0.1 * k  # the light: a different brightness per shot, divided out
        shots.append(torch.from_numpy(shifted).permute(2, 0, 1) * shade)
    r = shot_shifts(torch.stack(shots))
    assert r["shifts"][3] == pytest.approx([2.5, -1.5], abs=0.35), r  # cv2.phaseCorrelate: ±0.3 px at half pixels
    # the others against a mean that holds the moved shot at 1/4: a fraction of its shift, well below it
    assert all(r["magnitude"][k] < 0.6 for k in (0, 1, 2, 4)), r
    assert r["max"] == pytest.approx(r["magnitude"][3])
