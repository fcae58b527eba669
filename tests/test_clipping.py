"""How a clipped channel is read (torchmetal.clipping): chosen on left-out shots."""

from dataclasses import replace

import pytest
import torch

from torchmetal.clipping import choose_clipping, partly_clipped, pixel_clipped, with_clipping
from torchmetal.errors import InputError
from torchmetal.synth import synth_capture


def _clipped(seed=3):
    """A sensor clipping each channel on its own: bright yellow-ish highlights clip red and green first."""
    r = synth_capture(size=64, shots=8, seed=seed, texture="procedural", s=(0.9, 0.8, 0.4), alpha=(60.0, 60.0, 60.0),
                      layout="ring", bits=16, exposure=2.5, noise=0.002)
    return r.capture


def _camera_processed(cap):
    """What a phone makes of it: where a channel clipped, the others are pulled halfway towards white (the
    highlight roll-off after white balance and the colour matrix), the clip flags left as recorded."""
    hit = cap.saturated.any(1, keepdim=True)
    rolled = cap.images + 0.5 * (1.0 - cap.images).clamp_min(0.0)
    return replace(cap, images=torch.where(hit, rolled, cap.images))


def test_pixel_reading_marks_every_channel():
    cap = _clipped()
    n = partly_clipped(cap)
    assert n > 0  # the test scene has partly clipped observations
    px = pixel_clipped(cap)
    assert partly_clipped(px) == 0 and torch.equal(px.saturated.all(1), cap.saturated.any(1))
    assert torch.equal(px.images, cap.images) and px is not cap


def test_an_honest_sensor_keeps_each_channel():
    mode, d = choose_clipping(_clipped())
    assert mode == d.chosen == "channel" and d.reference == "channel", d.reason
    assert set(d.mse) == {"channel", "pixel"} and "partly clipped" in d.reason


def test_a_processed_photo_drops_the_whole_observation():
    """The other channels of a clipped observation are wrong: reading them biases the fit (the card's white
    gold specular); dropping them predicts left-out shots better."""
    cap = _camera_processed(_clipped())
    mode, d = choose_clipping(cap)
    assert mode == d.chosen == "pixel", d.reason
    assert d.z["pixel"] > 4 and d.mse["pixel"] < d.mse["channel"]
    out, rep = with_clipping(cap, "auto")
    assert rep["chosen"] == "pixel" and rep["decision"]["name"] == "clipping" and partly_clipped(out) == 0


def test_nothing_partly_clipped_is_not_tested():
    cap = synth_capture(size=32, shots=6, seed=1, texture="procedural").capture
    mode, d = choose_clipping(cap)
    assert mode == "channel" and "no observation" in d.reason and not d.mse
    out, rep = with_clipping(cap, "channel")
    assert out is cap and rep == {"mode": "channel", "chosen": "channel"}
    with pytest.raises(InputError, match="clipping: expected one of"):
        with_clipping(cap, "any")


def test_the_shared_card_reads_clipping_per_pixel():
    """cards_blue (phone photos, 1 % of observations partly clipped): pixel predicts its left-out shots 3 %
    better (z ~36); read per channel its gold specular came out white and its foil edges purple."""
    from torchmetal.io.capture import load_capture
    from torchmetal.io.shared_data import shared_capture, shared_data_dir

    path = shared_capture("cards_blue")
    if path is None:
        pytest.skip(f"shared real capture cards_blue not found under {shared_data_dir()} (set TORCHMETAL_SHARED_DATA)")
    mode, d = choose_clipping(load_capture(path))
    assert mode == "pixel" and d.z["pixel"] > 10 and d.mse["pixel"] < 0.99 * d.mse["channel"], d.reason
