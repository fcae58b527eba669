"""Detection overlays (torchmetal.flakes.estimate.overlay): the PNG is written, sized right and marks detections."""

import math

import cv2
import numpy as np
import pytest
import torch

from tests.flakes.scenes import residual_scene
from torchmetal.errors import InputError
from torchmetal.flakes.estimate.detect import detect_flakes
from torchmetal.flakes.estimate.overlay import overlay_detections, save_detection_overlay
from torchmetal.flakes.estimate.regions import PixelList, region_moments
from torchmetal.flakes.estimate.results import Particles
from torchmetal.io.images import linear_to_srgb

RED = (255, 40, 40)


def particles(rows) -> Particles:
    """A hand-made table: rows of (cy, cx, major, minor, angle)."""
    t = torch.tensor(rows, dtype=torch.float32).reshape(-1, 5)
    n = t.shape[0]
    z = torch.zeros(n)
    return Particles(
        shot=torch.zeros(n, dtype=torch.int64), area=torch.ones(n), cy=t[:, 0], cx=t[:, 1], major=t[:, 2],
        minor=t[:, 3], angle=t[:, 4], rgb=torch.zeros(n, 3), lab=torch.zeros(n, 3), peak=torch.zeros(n, 3),
        amp=z, snr=z, flux=z, sigma=z,
    )


def marked(pic: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels tinted towards the outline colour (anti-aliased edges included)."""
    p = pic.astype(np.int32)
    return (p[..., 0] - p[..., 1] > 40) & (p[..., 0] - p[..., 2] > 40)


class TestOverlay:
    def test_smoke_shape_dtype(self):
        pic = overlay_detections(torch.full((3, 20, 30), 0.2), particles([(10.5, 15.5, 6, 4, 0.0)]))
        assert pic.shape == (20, 30, 3) and pic.dtype == np.uint8 and pic.flags["C_CONTIGUOUS"]

    def test_no_particles_is_the_srgb_image(self):
        img = torch.rand(3, 16, 24, generator=torch.Generator().manual_seed(0))
        pic = overlay_detections(img, particles([]), gain=1.5)
        ref = (linear_to_srgb((img * 1.5).clamp(0.0, 1.0)) * 255 + 0.5).to(torch.uint8).permute(1, 2, 0).numpy()
        assert np.array_equal(pic, ref)  # RGB order, no BGR swap

    def test_outline_position_size_and_angle(self):
        # one ellipse: major 20 px, minor 8 px, 30° from +col towards image up
        cy, cx, angle = 32.5, 40.5, math.radians(30)
        pic = overlay_detections(torch.zeros(3, 64, 80), particles([(cy, cx, 20.0, 8.0, angle)]))
        m = marked(pic)
        i, j = np.nonzero(m)
        assert abs(i.mean() + 0.5 - cy) < 0.5 and abs(j.mean() + 0.5 - cx) < 0.5
        r = np.hypot(i + 0.5 - cy, j + 0.5 - cx)
        assert 9.0 < r.max() < 11.5 and 3.0 < r.min() < 5.0  # semi-axes 10 and 4
        px = PixelList(torch.zeros(len(i), dtype=torch.int64), torch.zeros(len(i), dtype=torch.int64),
                       torch.from_numpy(i), torch.from_numpy(j), 1)
        ink = torch.from_numpy(pic[i, j, 0].astype(np.float64))  # anti-aliasing weights
        got = float(region_moments(px, ink)["angle"][0])
        assert abs(got - angle) < math.radians(2)  # same convention as region_moments
        r, g, b = pic[m][np.argmax(pic[m][:, 0])].astype(float)  # the most inked pixel has the outline hue
        assert r > 200 and abs(g - r * RED[1] / RED[0]) < 12 and abs(b - r * RED[2] / RED[0]) < 12

    def test_small_particles_get_min_radius(self):
        pic = overlay_detections(torch.zeros(3, 32, 32), particles([(16.5, 16.5, 0.5, 0.5, 0.0)]), min_radius=3.0)
        i, j = np.nonzero(marked(pic))
        r = np.hypot(i + 0.5 - 16.5, j + 0.5 - 16.5)
        assert len(i) > 8 and 2.0 < r.mean() < 4.0

    def test_marks_every_detection(self):
        sc = residual_scene(64, 128, shots=1, edge_margin=16, seed=3)
        det = detect_flakes(sc.photos, sc.phong, sc.irradiance)
        p = det.particles.for_shot(0)
        assert len(p) > 10
        pic = overlay_detections(sc.photos[0], p, gain=1.0, min_radius=2.5)
        m = marked(pic)
        yy, xx = np.mgrid[0:64, 0:128] + 0.5
        for cy, cx, major in zip(p.cy.tolist(), p.cx.tolist(), p.major.tolist()):
            near = np.hypot(yy - cy, xx - cx) <= max(2.5, 0.5 * major) + 1.5
            assert m[near].any()
        # nothing marked far from every detection
        d = np.min(np.hypot(yy[..., None] - p.cy.numpy(), xx[..., None] - p.cx.numpy()), -1)
        assert not m[d > 0.5 * float(p.major.max()) + 4].any()

    def test_bad_input(self):
        with pytest.raises(InputError, match="image"):
            overlay_detections(torch.zeros(16, 16, 3), particles([]))
        with pytest.raises(InputError, match="image"):
            overlay_detections(torch.zeros(1, 3, 16, 16), particles([]))


class TestSaveOverlay:
    def test_png_written_with_size_and_marks(self, tmp_path):
        img = torch.full((3, 40, 60), 0.1)
        path = save_detection_overlay(tmp_path / "sub" / "overlay.png", img, particles([(20.5, 30.5, 12, 6, 0.3)]))
        assert path.exists() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert back.shape == (40, 60, 3) and back.dtype == np.uint8
        rgb = back[:, :, ::-1]
        assert np.array_equal(rgb, overlay_detections(img, particles([(20.5, 30.5, 12, 6, 0.3)])))
        assert marked(rgb).any()

    def test_kwargs_forwarded(self, tmp_path):
        img = torch.full((3, 24, 24), 0.1)
        p = particles([(12.5, 12.5, 10, 10, 0.0)])
        path = save_detection_overlay(tmp_path / "g.png", img, p, color=(40, 255, 40), gain=2.0)
        rgb = cv2.imread(str(path))[:, :, ::-1].astype(np.int32)
        assert ((rgb[..., 1] - rgb[..., 0]) > 100).any()

    @pytest.mark.parametrize("name", ["overlay.xyz", "overlay"])
    def test_not_a_png_path(self, tmp_path, name):
        with pytest.raises(InputError, match="png") as err:
            save_detection_overlay(tmp_path / name, torch.zeros(3, 8, 8), particles([]))
        assert "\n" not in str(err.value)

    def test_unwritable_path(self, tmp_path):
        blocker = tmp_path / "file"
        blocker.write_text("x")
        with pytest.raises(InputError) as err:
            save_detection_overlay(blocker / "overlay.png", torch.zeros(3, 8, 8), particles([]))
        assert "\n" not in str(err.value)
