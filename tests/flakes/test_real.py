"""The flake stage on the real capture ../shared/data/cards_blue (skipped when the data is absent).

cards_blue is a flash-at-the-lens smartphone capture of glittery card (7 shots, 1024²). Its
faint detections are mostly the coating's misfit on a velvety texture (the mirrored residual has
as many): the statistics detect only where the positive spots outnumber the mirrored ones twenty
to one (null_test.glint_snr: 20σ here), so the model is built from the bright glints. Shot 3 is
left out and rendered with and without the flake term.
"""


import pytest
import torch

from torchmetal.flakes.estimate.overlay import save_detection_overlay
from torchmetal.flakes.model import MAX_DENSITY
from torchmetal.flakes.model.md import metallic_difference
from torchmetal.io.capture import load_capture
from torchmetal.io.shared_data import shared_data_dir
from torchmetal.pipeline import fit_material
from torchmetal.renderer import MaterialRenderer

DATA = shared_data_dir()
HOLD = 3


@pytest.fixture(scope="module")
def cards_blue():
    path = DATA / "cards_blue"
    if not (path / "capture.json").is_file():
        pytest.skip(f"shared data cards_blue not present at {path}")
    cap = load_capture(path)
    fit_cap = cap.subset([k for k in range(cap.num_shots) if k != HOLD])
    return fit_cap, cap.subset([HOLD]), fit_material(fit_cap, flakes="on", seed=0)


def test_statistics_are_fitted(cards_blue):
    _, _, res = cards_blue
    model, rep = res.material.flakes, res.flakes.report
    assert model is not None, rep.get("skipped")
    assert rep["detection_snr"] > 5.0  # raised above the detector's 5σ: the faint spots are misfit
    assert model.density == pytest.approx(min(rep["density"], MAX_DENSITY))
    assert 0.02 < model.tilt_sigma < 0.5 and 1e-3 < model.glint_sigma < 0.2
    assert all(0.0 < c < 1.0 for c in model.color_mean)
    assert rep["identified"]["log_amp_mean"]  # the flakes' brightness: standard error 0.006-0.009 in every run


@pytest.mark.xfail(strict=False, reason=(
    "open: whether the card's tilt and glint σ count as identified (standard error < 0.15) is knife-edge: the "
    "photos times (1 + 1e-6·noise) move glint σ's standard error 0.086 -> 0.191 at 5281ce8, and the plane render's "
    "float rounding moves both to 0.45 / 1.30 with the estimates unchanged (tilt 0.113 vs 0.114, glint 0.0303 vs "
    "0.0298): docs/measurements.md 2026-12-07"))
def test_tilt_and_glint_width_are_identified(cards_blue):
    _, _, res = cards_blue
    ident = res.flakes.report["identified"]
    assert ident["log_tilt_sigma"] and ident["log_glint_sigma"]


def test_flake_term_lowers_md_of_the_left_out_shot(cards_blue):
    _, one, res = cards_blue
    md = {}
    with torch.inference_mode():
        for flakes in (True, False):
            img = MaterialRenderer(res.material, flakes=flakes)(one.lights.float(), one.intensities.float(), one.cameras.float())
            assert bool(torch.isfinite(img).all())
            md[flakes] = float(metallic_difference(img, one.images.float()))
    assert md[True] < 0.95 * md[False]  # measured: 52.4 with, 60.7 without (5σ detections: 31.9, 57.1)


def test_sparkles_carry_no_more_energy_than_the_photo_shows(cards_blue):
    """The rendered sparkles' energy on the left-out shot, against the photo's positive high-pass excess over
    the flake-free render (its positive minus its negative part: misfit is both): measured 0.5 (with every
    5σ detection a flake it was 2–4, and the render a field of dots the photo does not show)."""
    from torchmetal.flakes.model.filters import box_mean

    _, one, res = cards_blue
    with torch.inference_mode():
        args = (one.lights.float(), one.intensities.float(), one.cameras.float())
        sparkly, plain = (MaterialRenderer(res.material, flakes=f)(*args) for f in (True, False))
    valid = (one.mask & ~one.saturated[0].any(0, keepdim=True)).expand_as(plain[0])
    r = one.images.float() - plain
    hp = (r - box_mean(r, 7))[0][valid]
    excess = float((hp.clamp_min(0) ** 2).mean() - (hp.clamp_max(0) ** 2).mean())
    energy = float(((sparkly - plain)[0][valid] ** 2).mean())
    assert excess > 0 and 0 < energy < 1.2 * excess, (energy, excess)


def test_overlay_png(cards_blue, tmp_path):
    fit_cap, _, res = cards_blue
    parts = res.flakes.particles.for_shot(0)
    out = save_detection_overlay(tmp_path / "flakes.png", fit_cap.images[0], parts, gain=4.0)
    assert out.is_file() and out.stat().st_size > 10_000 and len(parts) > 10


def test_matte_sphere_gets_no_invented_flakes():
    """uw_gray_sphere is a matte painted ball: its sheen and rim leave positive residuals, bands ~200 px long,
    that passed the noise tests as glints (the flakes they gave had their normals at random and moved the
    left-out shots' sparkle statistics away from the photos, MD ~43 vs ~9). Only spots count as glints: the
    pixel screen stops the stage before any detection, and the material is the flake-free one."""
    path = DATA / "uw_gray_sphere"
    if not (path / "capture.json").is_file():
        pytest.skip(f"shared data uw_gray_sphere not present at {path}")
    cap = load_capture(path)
    res, off = fit_material(cap, seed=0), fit_material(cap, seed=0, flakes="off")
    rep = res.report["flakes"]
    assert res.material.flakes is None and "screen" in rep and "degenerate" not in rep, rep.get("skipped")
    assert torch.equal(res.material.texture, off.material.texture)
