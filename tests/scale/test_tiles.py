"""The tiled capture format: converter and region reads give the loader's values."""

import json

import numpy as np
import pytest
import torch

from torchmetal.errors import CaptureError
from torchmetal.io.capture import load_capture
from torchmetal.scale.tiles import TiledCapture, convert_capture, is_tiled


@pytest.fixture(scope="module")
def png_capture(tmp_path_factory):
    from torchmetal.synth import synth_capture, write_synth

    path = tmp_path_factory.mktemp("png") / "cap"
    write_synth(synth_capture(size=40, shots=4, seed=2, noise=0.003, bumpy=True, bits=16), path)
    meta = json.loads((path / "capture.json").read_text())
    mask = np.ones((40, 40), np.uint8) * 255
    mask[:5, :7] = 0
    import cv2

    cv2.imwrite(str(path / "mask.png"), mask)
    first = path / meta["shots"][0]["image"]
    img = cv2.imread(str(first), cv2.IMREAD_UNCHANGED)
    img[10:14, 20:26, 1] = np.iinfo(img.dtype).max  # clipped values: saturated
    cv2.imwrite(str(first), img)
    meta["mask"] = "mask.png"
    (path / "capture.json").write_text(json.dumps(meta))
    return path


def test_convert_gives_the_loaders_values(png_capture, tmp_path):
    assert not is_tiled(png_capture)
    dst = convert_capture(png_capture, tmp_path / "tiled")
    assert is_tiled(dst) and sorted(p.suffix for p in (dst / "images").iterdir()) == [".npy"] * 4
    a, b = load_capture(png_capture), load_capture(dst)
    for name in ("images", "saturated", "mask", "normals", "lights", "intensities", "cameras"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert a.size == b.size and bool(a.saturated.any())  # the synthetic highlights clip


def test_region_reads_match_the_loaded_capture(png_capture, tmp_path):
    dst = convert_capture(png_capture, tmp_path / "tiled")
    full, tc = load_capture(dst), TiledCapture(dst)
    assert tuple(tc.images.shape) == tuple(full.images.shape) and not tc.flat_normals
    for rows, cols in [(slice(3, 40, 7), slice(3, 40, 7)), (slice(8, 24), slice(30, 40)), (slice(None), slice(None))]:
        assert torch.equal(tc.images[..., rows, cols], full.images[..., rows, cols])
        assert torch.equal(tc.saturated[..., rows, cols], full.saturated[..., rows, cols])
        assert torch.equal(tc.mask[..., rows, cols], full.mask[..., rows, cols])
        assert torch.equal(tc.normals[:, rows, cols], full.normals[:, rows, cols])


def test_bad_tiled_captures(png_capture, tmp_path):
    with pytest.raises(CaptureError, match="expected .npy images"):
        TiledCapture(png_capture)
    dst = convert_capture(png_capture, tmp_path / "tiled")
    np.save(dst / "images" / "001.npy", np.zeros((10, 40, 3), np.float32))
    with pytest.raises(CaptureError, match="expected size 40x40"):
        TiledCapture(dst)
    np.save(dst / "images" / "001.npy", np.full((40, 40, 3), np.nan, np.float32))
    with pytest.raises(CaptureError, match="non-finite"):
        TiledCapture(dst).images[..., 0:8, 0:8]
