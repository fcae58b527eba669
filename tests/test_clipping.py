"""How a clipped channel is read (torchmetal.clipping); the choice is tested in tests/select/test_choices.py."""

from dataclasses import replace

import torch

from torchmetal.clipping import partly_clipped, pixel_clipped
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
