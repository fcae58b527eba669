"""The choices before the Phong fit (torchmetal.select.choices): clipping, normals, relief, light, each through
the harness with the reference fit's model; their screens; the misfires they must not make."""

from dataclasses import replace

import pytest
import torch

import torchmetal.select.choices as sc
from tests.lightcal.helpers import flash_capture, photographed
from tests.normals.test_relief import _embossed
from torchmetal.clipping import partly_clipped, with_clipping
from torchmetal.errors import InputError
from torchmetal.geometry import shading_geometry
from torchmetal.lightcal import LightCalibration, with_light
from torchmetal.normals import with_normals
from torchmetal.phong import phong_shading
from torchmetal.select.choices import CLIPPING, LIGHT, NORMALS, REGISTRATION, RELIEF, choose
from torchmetal.select.rule import TYPICAL_GAIN, z_min_for
from torchmetal.synth import synth_capture


@pytest.fixture(scope="module")
def bumpy():
    return synth_capture(size=64, shots=12, seed=3, noise=0.003, bumpy=True).capture


@pytest.fixture(scope="module")
def flat():
    return synth_capture(size=64, shots=8, seed=4, noise=0.003).capture


def two_materials(size=64, shots=12, seed=2, noise=0.002):
    """A flat sample of two materials of different gloss (left half s 0.6, α 200; right s 0.2, α 15), exact lights:
    one global lobe misfits it, and a relief, estimated normals or a moved light "explain" that misfit."""
    base = synth_capture(size=size, shots=shots, seed=seed, noise=0.0, layout="hemisphere").capture
    g = torch.Generator().manual_seed(seed)
    tex = 0.1 + 0.5 * torch.rand(3, size, size, generator=g)
    geom = shading_geometry(base.normals, base.lights, base.intensities, base.cameras, base.size)
    left = phong_shading(tex, torch.full((3,), 0.6), torch.full((3,), 200.0), geom)
    right = phong_shading(tex, torch.full((3,), 0.2), torch.full((3,), 15.0), geom)
    clean = torch.where(torch.arange(size).view(1, 1, 1, size) < size // 2, left, right)
    images = clean * (1.0 + noise * torch.randn(clean.shape, generator=g))
    return replace(base, images=images)


# ----------------------------------------------------------------------------- normals and relief


def test_bumpy_sample_gets_estimated_normals(bumpy):
    """Each shot left out alone, the normals fitted on the other 11 halve the typical pixel's held-out error (with
    three groups of shots left out, trained on 8, only by 46 %, under TYPICAL_GAIN: normals kept flat)."""
    d = choose(NORMALS, replace(bumpy, normals=None))
    assert d.chosen == "estimate" and d.z["estimate"] > z_min_for("normals"), d.reason
    assert d.scores["log_ratio"]["estimate"]["gain"] >= TYPICAL_GAIN
    assert d.holds == [[k] for k in range(12)]
    assert d.scores["screen"]["run"] and d.mse["estimate"] < d.mse["flat"] and d.seconds > 0


def test_flat_sample_is_screened_and_stays_flat(flat):
    d = choose(NORMALS, flat)
    assert d.chosen == "flat" == d.reference and not d.mse, d.reason  # no candidate fit at all
    assert not d.scores["screen"]["run"] and d.scores["screen"]["tilt_share"] < sc.tilt_screen.__globals__["TILT_SHARE"]


def test_the_tilt_screen_asks_for_size_not_only_significance(bumpy):
    """The bumpy sample's tilts explain most of the typical pixel's residual: above both tests' floors; a floor
    above the reading screens the test out with the reading in the reason, and the floor changes nothing else."""
    cap = replace(bumpy, normals=None)
    fit = sc.reference_context(cap, dict(sc.DEFAULT_FIT)).fit(cap)
    run = sc.tilt_screen(fit, cap)
    explained = run.reading["explained_median"]
    assert run.run and max(sc.NORMALS_EXPLAINED, sc.RELIEF_EXPLAINED) < explained <= 1.0
    stop = sc.tilt_screen(fit, cap, min_explained=min(1.0, explained + 0.01))
    assert not stop.run and stop.reading == run.reading and f"tilts explain {explained:.1%}" in stop.reason


def test_given_normals_and_too_few_shots_are_not_tested(bumpy):
    d = choose(NORMALS, bumpy)
    assert d.chosen == "flat" and "own normals" in d.reason and not d.holds  # the pipeline then keeps "given"
    d = choose(NORMALS, replace(bumpy, normals=None).subset([0, 1, 2]))
    assert d.chosen == "flat" and not d.holds and not d.mse and not d.pixels and "needs >= 4 shots" in d.reason


def test_a_flat_normal_map_is_kept_by_auto(flat, tmp_path):
    """A capture's own normals.npy is kept, flat or not (docs/design.md §2.5): it is not tested against a relief."""
    from torchmetal.io.capture import load_capture
    from torchmetal.io.capture_save import save_capture
    from torchmetal.pipeline import fit_material

    given = replace(flat, normals=flat.normals.clone(), normals_given=True)  # replace() keeps the flag unless told
    assert given.normals_given and not flat.normals_given and given.flat
    save_capture(given, tmp_path / "cap")
    assert (tmp_path / "cap" / "normals.npy").is_file()
    loaded = load_capture(tmp_path / "cap")
    assert loaded.normals_given and loaded.subset([0, 1]).normals_given and loaded.downsampled(2).normals_given
    rep = fit_material(loaded.subset(list(range(5))), flakes="off", light="off", clipping="channel").report
    assert rep["normals"]["chosen"] == "given" and [d["name"] for d in rep["decisions"]].count("relief") == 0


@pytest.mark.parametrize("n", [4, 5])
def test_every_fold_leaves_three_shots(bumpy, n):
    d = choose(NORMALS, replace(bumpy, normals=None).subset(list(range(n))))
    assert d.chosen in ("flat", "estimate") and d.holds and all(n - len(g) >= 3 for g in d.holds)


def test_the_test_stops_once_every_extension_is_worse_beyond_noise(flat, monkeypatch):
    real = sc.estimate_normals

    def tilted(train, **kw):  # normals 0.5 rad off: every left-out shot is predicted worse
        est = real(train, **kw)
        n = torch.stack([torch.full_like(est.normals[0], 0.48), torch.zeros_like(est.normals[0]),
                         torch.full_like(est.normals[0], 0.88)])
        return replace(est, normals=n / n.norm(dim=0, keepdim=True))

    monkeypatch.setattr(sc, "estimate_normals", tilted)
    d = choose(replace(NORMALS, screen=None), flat)  # the screen would skip it
    assert d.chosen == "flat" and d.z["estimate"] < -4
    n = flat.num_shots  # the normals leave one shot out at a time
    assert len(d.holds) == 1 and f"stopped after 1 of {n}" in d.reason  # the other shots were not fitted


def test_relief_of_an_embossed_sample_and_not_of_a_flat_one(flat):
    cap, _ = _embossed(5)
    d = choose(RELIEF, cap)
    assert d.chosen == "relief" and d.z["relief"] > 4 and "typical pixel" in d.reason, d.reason
    d = choose(RELIEF, flat)
    assert d.chosen == "flat", d.reason
    out, rep = with_normals(cap, "relief")
    assert not out.flat and rep["mode"] == "relief"
    with pytest.raises(InputError, match="auto is chosen by torchmetal.select"):
        with_normals(cap, "auto")


def test_relief_follows_estimated_normals(flat):
    d = choose(RELIEF, flat, chosen={"normals": "estimate"})
    assert d.chosen == "flat" and "estimated normals kept" in d.reason


# ----------------------------------------------------------------------------- the measured misfire


def test_a_flat_two_material_sample_takes_no_relief_normals_or_light_move():
    """Issue 41's misfire: a flat sample of two materials took a relief (and lost 28 dB) because the relief's
    test fitted one global lobe; every candidate is now fitted with the reference fit's model."""
    cap = two_materials()
    ctx = sc.reference_context(cap, dict(sc.DEFAULT_FIT))
    assert ctx.model["specular"] == "clustered", ctx.model  # the final fit's model: two materials
    for choice in (NORMALS, RELIEF, LIGHT):
        d = sc.decide(choice, cap, ctx)
        assert d.chosen == choice.reference, (choice.name, d.reason)
        # forced through the test, it still keeps the reference
        d = sc.decide(replace(choice, screen=None), cap, ctx)
        assert d.chosen == choice.reference, (choice.name, d.reason)


# ----------------------------------------------------------------------------- clipping


def _clipped(seed=3):
    """A sensor clipping each channel on its own: bright yellow-ish highlights clip red and green first."""
    return synth_capture(size=64, shots=8, seed=seed, texture="procedural", s=(0.9, 0.8, 0.4), alpha=(60.0, 60.0, 60.0),
                         layout="ring", bits=16, exposure=2.5, noise=0.002).capture


def _camera_processed(cap):
    """What a phone makes of it: where a channel clipped, the others are pulled halfway towards white."""
    hit = cap.saturated.any(1, keepdim=True)
    return replace(cap, images=torch.where(hit, cap.images + 0.5 * (1.0 - cap.images).clamp_min(0.0), cap.images))


def test_an_honest_sensor_keeps_each_channel():
    d = choose(CLIPPING, _clipped())
    assert d.chosen == d.reference == "channel", d.reason
    assert d.scores["screen"]["residual_share"] >= 0 and d.scores["screen"]["observations"] > 0
    forced = choose(replace(CLIPPING, screen=None), _clipped())  # tested, it keeps channel too
    assert forced.chosen == "channel" and set(forced.mse) == {"channel", "pixel"}, forced.reason


def test_a_processed_photo_drops_the_whole_observation():
    cap = _camera_processed(_clipped())
    d = choose(CLIPPING, cap)
    assert d.chosen == "pixel" and d.z["pixel"] > 4 and d.mse["pixel"] < d.mse["channel"], d.reason
    assert d.scores["screen"]["run"] and d.scores["screen"]["residual_share"] >= sc.clipping_screen.__globals__["CLIPPING_SHARE"]
    out, rep = with_clipping(cap, "pixel")
    assert rep["chosen"] == "pixel" and partly_clipped(out) == 0


def test_the_clipping_test_scores_pixels_both_readings_saw_in_training():
    """A held-out observation counts only where some training shot saw its pixel with no channel clipped: elsewhere
    the "pixel" reading has no data for the pixel's texture, and its guess there is not the reading's error."""
    cap = _camera_processed(_clipped())
    sat = cap.saturated.clone()
    sat[:, :, 3, 5] = False
    sat[2:, 0, 3, 5] = True  # red clipped in every shot but the first two
    cap = replace(cap, saturated=sat)
    seen = sc._clipping_hold(cap, [0, 4])  # shot 1 trains: it saw the pixel whole
    assert not seen.saturated[0, :, 3, 5].any() and seen.saturated[1, :, 3, 5].all()
    unseen = sc._clipping_hold(cap, [0, 1])  # no training shot saw it whole
    assert unseen.saturated[:, :, 3, 5].all()
    whole = ~sat[2:].any(1).all(0)  # (H, W) pixels some training shot of [0, 1] saw whole
    assert torch.equal(unseen.saturated[:, :, whole], sat[:2].any(1, keepdim=True).expand(-1, 3, -1, -1)[:, :, whole])


def test_a_processed_clip_that_hides_whole_pixels_from_a_fold_is_read_per_pixel(tmp_path):
    """Random scene 300 (8-bit, a phone's processed clip): in a fold, pixels clipped in every training shot have no
    texture under the "pixel" reading; scored there, the reading that recovers the truth lost at z −4.6 and the fit
    kept "channel", 27 dB below (docs/measurements.md, eighth session)."""
    from torchmetal.io.capture import load_capture
    from torchmetal.synth.random_scenes import make_random_case, random_scene

    rs = random_scene(300)
    assert rs.clip == "processed" and rs.scene.encoding == "srgb8"
    cap = load_capture(make_random_case(rs, tmp_path / rs.name).capture_dir)
    d = choose(CLIPPING, cap)
    assert d.chosen == "pixel", d.reason


def test_nothing_partly_clipped_is_not_tested():
    cap = synth_capture(size=32, shots=6, seed=1, texture="procedural").capture
    d = choose(CLIPPING, cap)
    assert d.chosen == "channel" and "no observation" in d.reason and not d.mse
    out, rep = with_clipping(cap, "channel")
    assert out is cap and rep == {"mode": "channel", "chosen": "channel"}
    for bad in ("any", "auto"):
        with pytest.raises(InputError, match="clipping: expected one of"):
            with_clipping(cap, bad)


def test_the_shared_card_tests_its_clipping():
    """cards_blue (phone photos, 1 % of observations partly clipped): their other channels hold about a tenth of the
    residual (at the screen's floor unregistered, 14 % after the pipeline's registration); tested, the outcome is
    recorded with both candidates' held-out errors (docs/measurements.md has it under each pairing)."""
    from torchmetal.io.capture import load_capture
    from torchmetal.io.shared_data import shared_capture, shared_data_dir

    path = shared_capture("cards_blue")
    if path is None:
        pytest.skip(f"shared real capture cards_blue not found under {shared_data_dir()} (set TORCHMETAL_SHARED_DATA)")
    cap = load_capture(path)
    screen = CLIPPING.screen(CLIPPING.grid(cap), sc.reference_context(cap, dict(sc.DEFAULT_FIT)))
    assert 0.05 < screen.reading["residual_share"] < 0.3
    d = choose(replace(CLIPPING, screen=None), cap)
    assert set(d.mse) == {"channel", "pixel"}, d.reason
    assert d.chosen in ("channel", "pixel") and (d.chosen == "pixel") == (d.z["pixel"] > z_min_for("clipping")), d.reason


# ----------------------------------------------------------------------------- light


def _light_capture(layout="near", shots=8, seed=5):
    return synth_capture(size=40, shots=shots, layout=layout, texture="procedural", seed=seed, noise=0.01).capture


def test_exact_lights_are_screened_and_kept():
    d = choose(LIGHT, _light_capture())
    assert d.chosen == "off" and not d.scores["screen"]["run"] and not d.mse, d.reason


def test_a_flash_beside_the_lens_is_found():
    """Every photo taken with the light 6 mm below and 2 mm above where capture.json puts it."""
    cap, move, _ = flash_capture()
    d = choose(LIGHT, cap)
    assert d.chosen == "flash" and d.scores["screen"]["run"] and d.z["flash"] > 4, d.reason
    out, cal, rep = with_light(cap, "flash")
    found = torch.tensor(cal.flash, dtype=torch.float64)
    assert float((found - move)[:2].norm()) < 0.2 * float(move[:2].norm())
    assert cal.offsets is None and cal.for_unseen() == cal and torch.equal(out.lights, cal.lights(cap))


def test_no_highlight_no_move():
    """A matte sample photographed with the flash moved: the reference fit keeps no specular lobe, and a
    diffuse-only fit's misfit moves the lights as readily as a misplaced flash does: the capture's lights stay."""
    r = synth_capture(size=40, shots=8, layout="near", texture="procedural", seed=5, s=(0.0, 0.0, 0.0))
    move = torch.tensor((0.0, -0.006, 0.002), dtype=torch.float64)
    cap, _ = photographed(r, move.expand(8, 3), 0.01, torch.Generator().manual_seed(7))
    d = choose(LIGHT, cap)
    assert d.chosen == "off" and "no specular lobe" in d.reason, d.reason


def test_light_skips_are_reported():
    d = choose(LIGHT, _light_capture(layout="far"))
    assert d.chosen == "off" and "directional" in d.reason
    d = choose(LIGHT, _light_capture(shots=3))
    assert d.chosen == "off" and not d.mse
    _, cal, rep = with_light(_light_capture(layout="far"), "falloff")
    assert cal.identity and rep["skipped"]
    with pytest.raises(InputError, match="light: expected one of"):
        with_light(_light_capture(), "auto")
    assert LightCalibration().identity


# ----------------------------------------------------------------------------- registration

SHIFTS = [[0, 0], [3, 0], [0, -2], [4, 3], [-3, 1], [0, 0], [2, -4], [-2, -2]]  # px, x right and y down


def _misregistered(capture, shifts=SHIFTS):
    """``capture`` with each shot moved by ``shifts`` (a rectification's residual), the pixels moved in from outside
    clipped in every channel."""
    from torchmetal.registration import moved

    m = moved(capture.images, shifts, sign=1.0)
    return replace(capture, images=torch.nan_to_num(m, nan=0.0), saturated=capture.saturated | torch.isnan(m))


@pytest.fixture(scope="module")
def textured():
    return synth_capture(size=96, shots=8, seed=3, noise=0.003, texture="procedural").capture


def test_registered_shots_are_not_tested(textured):
    d = choose(REGISTRATION, textured)
    assert d.chosen == "off" and not d.mse and "registered within" in d.reason, d.reason


def test_shots_off_by_pixels_are_moved_back(textured):
    from torchmetal.registration import shot_shifts, with_registration

    bad = _misregistered(textured)
    d = choose(REGISTRATION, bad)
    assert d.chosen == "shift" and d.mse["shift"] < 0.8 * d.mse["off"] and d.z["shift"] > 4, d.reason
    fixed, rep = with_registration(bad, "shift")
    assert rep["chosen"] == "shift" and rep["max"] > 2.0
    assert shot_shifts(fixed.images)["max"] < 0.5 * rep["max"]  # what is left of the shifts after moving back
    with pytest.raises(InputError, match="registration: expected one of"):
        with_registration(bad, "affine")


def test_moved_there_and_back_is_the_image_inside():
    from torchmetal.registration import moved

    x = torch.rand(2, 3, 20, 24, dtype=torch.float64)
    there = moved(x, [[2.0, -1.0], [0.0, 3.0]], sign=1.0)
    back = moved(torch.nan_to_num(there, nan=0.0), [[2.0, -1.0], [0.0, 3.0]])
    inside = ~torch.isnan(there) & ~torch.isnan(back)
    inside[..., :4, :] = inside[..., -4:, :] = inside[..., :, :4] = inside[..., :, -4:] = False
    assert bool(torch.isnan(there[0, :, :, :2]).all()) and torch.allclose(back[inside], x[inside])
