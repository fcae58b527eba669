"""normals="auto" (torchmetal.normals.choice): estimated normals only where left-out shots prefer them."""

from dataclasses import replace

import pytest
import torch

from torchmetal.geometry import surface_points
from torchmetal.normals import choose_normals, strided_capture, with_normals
from torchmetal.synth import synth_capture


@pytest.fixture(scope="module")
def bumpy():
    return synth_capture(size=64, shots=8, seed=3, noise=0.003, bumpy=True).capture


@pytest.mark.parametrize("h,w,max_pixels", [(64, 64, 300), (101, 70, 500), (50, 97, 100)])
def test_strided_capture_keeps_each_pixel_where_it_was(bumpy, h, w, max_pixels):
    cap = replace(bumpy, images=torch.rand(3, 3, h, w), normals=None, mask=None, saturated=None,
                  lights=bumpy.lights[:3], intensities=bumpy.intensities[:3], cameras=bumpy.cameras[:3], names=[])
    sub = strided_capture(cap, max_pixels)
    hs, ws = sub.images.shape[-2:]
    assert hs * ws <= max_pixels and hs >= 2 and ws >= 2
    # the kept pixels: the centres of the sub-capture's grid are pixel centres of the capture, and the images agree
    full = surface_points(h, w, cap.size, dtype=torch.float64)
    part = surface_points(hs, ws, sub.size, dtype=torch.float64)
    rows = [int(torch.argmin((full[1, :, 0] - y).abs())) for y in part[1, :, 0]]
    cols = [int(torch.argmin((full[0, 0, :] - x).abs())) for x in part[0, 0, :]]
    assert torch.allclose(full[:, rows][:, :, cols], part, atol=1e-9)
    assert torch.equal(sub.images, cap.images[:, :, rows][..., cols])


def test_bumpy_sample_gets_estimated_normals(bumpy):
    mode, d = choose_normals(replace(bumpy, normals=None))
    assert mode == "estimate" == d.chosen and d.z["estimate"] > 4, d.reason
    cap, rep = with_normals(replace(bumpy, normals=None), "auto")
    assert rep["mode"] == "auto" and rep["chosen"] == "estimate" and not cap.flat
    assert rep["decision"]["mse"]["estimate"] < rep["decision"]["mse"]["flat"]


def test_flat_sample_stays_flat_and_given_normals_are_kept(bumpy):
    flat = synth_capture(size=64, shots=8, seed=4, noise=0.003).capture
    mode, d = choose_normals(flat)
    assert mode == "flat" == d.chosen == d.reference and d.holds and d.mse  # compared on left-out shots, flat kept
    cap, rep = with_normals(bumpy, "auto")
    assert cap is bumpy and rep["chosen"] == "given"


def test_too_few_shots_stay_flat(bumpy):
    mode, d = choose_normals(replace(bumpy, normals=None).subset([0, 1, 2]))
    assert mode == "flat" == d.chosen and not d.holds and not d.mse and not d.pixels  # 3 shots: no left-out test


@pytest.mark.parametrize("n", [4, 5])
def test_every_fold_leaves_the_estimate_three_shots(bumpy, n):
    mode, d = choose_normals(replace(bumpy, normals=None).subset(list(range(n))))
    assert mode in ("flat", "estimate") and all(n - len(g) >= 3 for g in d.holds) and d.holds


def test_the_test_stops_after_a_group_where_the_estimate_is_already_worse_beyond_noise(bumpy, monkeypatch):
    import torchmetal.normals.choice as nc

    flat = synth_capture(size=64, shots=8, seed=4, noise=0.003).capture
    real = nc.estimate_normals

    def tilted(train, **kw):  # normals 0.5 rad off: every left-out shot is predicted worse
        est = real(train, **kw)
        n = torch.stack([torch.full_like(est.normals[0], 0.48), torch.zeros_like(est.normals[0]),
                         torch.full_like(est.normals[0], 0.88)])
        return replace(est, normals=n / n.norm(dim=0, keepdim=True))

    monkeypatch.setattr(nc, "estimate_normals", tilted)
    mode, d = choose_normals(flat)
    assert mode == "flat" and d.z["estimate"] < -4
    assert len(d.holds) == 1 and "stopped after 1 of 3" in d.reason  # the other groups were not fitted
