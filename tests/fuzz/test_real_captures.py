"""The fuzz property on the shared real captures: made small, fitted with a few option sets, same property.

Each capture (``$TORCHMETAL_SHARED_DATA``, default ``../shared/data`` beside the repository) is
loaded, then made ≤ 96 px two ways and re-saved in a temporary directory: the whole sample
box-downsampled, and a native-resolution crop (lights and cameras moved with the crop's centre, so
the geometry of docs/design.md §2.1 holds and the real glints stay sharp). Each capture is fitted with two
option sets, one per way; every run must end with a complete material or a one-line error.
"""

from __future__ import annotations

import functools
import math
import tempfile
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from tests.fuzz.harness import check_outcome, fresh_output, run_fit, threads_one
from torchmetal.io.shared_data import shared_data_dir

threads_one()

REPO = Path(__file__).resolve().parents[2]
DATA = shared_data_dir()
CAPTURES = ["cards_blue", "yellow_box", "uw_gray_sphere"]
MAX_PX = 96
#: per capture, (how it is made small, fit options): two option sets each, kept to ~15 s in all
RUNS = {
    "cards_blue": [("crop", []), ("down", ["--flakes", "on", "--robust", "huber", "--lobe", "auto"])],
    "yellow_box": [("down", []), ("crop", ["--normals", "estimate", "--specular", "maps"])],
    "uw_gray_sphere": [("down", []), ("crop", ["--scheme", "paper", "--flakes", "off"])],
}


@functools.cache
def _full(name: str):
    from torchmetal.io.capture import load_capture

    return load_capture(DATA / name)


def _rebuild(cap, images, saturated, normals, mask, size, shift=(0.0, 0.0)):
    """A Capture with new pixels and surface size; point lights / cameras moved by -shift (x, y)."""
    from torchmetal.io.capture import Capture

    def move(t):
        t = t.clone()
        pos = t[:, 3] == 1
        t[pos, 0] -= shift[0]
        t[pos, 1] -= shift[1]
        return t

    return Capture(images=images.contiguous(), saturated=saturated.contiguous(), normals=normals, mask=mask,
                   lights=move(cap.lights), intensities=cap.intensities.clone(), cameras=move(cap.cameras),
                   size=size, names=list(cap.names), color_space=cap.color_space)


@functools.cache
def small(name: str, how: str):
    """The capture ``name`` at ≤ MAX_PX: "down" (whole, box-averaged) or "crop" (centre, native pixels)."""
    cap = _full(name)
    h, w = cap.height, cap.width
    normals = None if cap.flat else cap.normals
    if how == "down":
        f = max(1, math.ceil(max(h, w) / MAX_PX))
        hh, ww = h // f * f, w // f * f  # whole blocks only: the box keeps the geometry when the crop is centred
        ci, cj = (h - hh) // 2, (w - ww) // 2
        crop = lambda t: t[..., ci:ci + hh, cj:cj + ww]  # noqa: E731
        images = F.avg_pool2d(crop(cap.images), f)
        saturated = F.max_pool2d(crop(cap.saturated).float(), f) > 0
        mask = -F.max_pool2d(-crop(cap.mask).float()[None], f)[0] > 0  # a block is sample where all of it is
        if normals is not None:
            normals = F.normalize(F.avg_pool2d(crop(normals)[None], f)[0], dim=0)
        i0, j0, sh, sw = ci, cj, hh, ww
    else:
        sh, sw = min(h, MAX_PX), min(w, MAX_PX)
        i0, j0 = (h - sh) // 2, (w - sw) // 2
        sl = lambda t: t[..., i0:i0 + sh, j0:j0 + sw]  # noqa: E731
        images, saturated, mask = sl(cap.images), sl(cap.saturated), sl(cap.mask)
        normals = sl(normals).contiguous() if normals is not None else None
    width, height = cap.size
    size = (width * sw / w, height * sh / h)
    # the crop's centre on the original surface (docs/design.md §2.1: row 0 is +y)
    x_c = ((j0 + sw / 2) / w - 0.5) * width
    y_c = (0.5 - (i0 + sh / 2) / h) * height
    return _rebuild(cap, images, saturated, normals, mask.contiguous(), size, (x_c, y_c))


@pytest.mark.slow
@pytest.mark.parametrize("name", CAPTURES)
def test_real_capture_small_fits_end_with_material_or_one_line(name):
    if not (DATA / name / "capture.json").is_file():
        pytest.skip(f"shared real capture {name} not found under {DATA} (set TORCHMETAL_SHARED_DATA)")
    from torchmetal.io.capture_save import save_capture

    for how, options in RUNS[name]:
        cap = small(name, how)
        assert max(cap.height, cap.width) <= MAX_PX and bool(torch.isfinite(cap.images).all())
        with tempfile.TemporaryDirectory(prefix="tm-fuzz-real-") as tmp:
            root = save_capture(cap, Path(tmp) / "cap")
            out = fresh_output(Path(tmp))
            check_outcome(run_fit(root, out, options), out, f"real captures (<= {MAX_PX} px)")
