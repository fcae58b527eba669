"""Capture directories: exact round trips, atomic saves, saturation, one-line errors for bad input."""

import json
import math
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchmetal.errors import CaptureError, InputError
from torchmetal.io.capture import Capture, check_light_camera, load_capture
from torchmetal.io.capture_save import save_capture
from torchmetal.io.images import code_table, srgb_to_linear, write_image
from torchmetal.io.shared_data import shared_data_dir

DATA = shared_data_dir()


def one_line(exc_info, *words):
    msg = str(exc_info.value)
    assert msg and "\n" not in msg, msg
    for w in words:
        assert w in msg, (w, msg)


def make_capture(n=3, h=6, w=5, seed=0, normals=False, mask=False, saturated=False, directional=False):
    g = torch.Generator().manual_seed(seed)
    images = torch.rand(n, 3, h, w, generator=g) * 0.9
    lights = torch.cat([torch.rand(n, 2, generator=g) * 0.1 - 0.05, torch.full((n, 1), 0.3), torch.ones(n, 1)], 1)
    if directional:
        lights[:, 3] = 0.0
    cameras = torch.tensor([[0.01, -0.02, 0.3, 1.0]]).repeat(n, 1)
    kw = {}
    if normals:
        nrm = torch.rand(3, h, w, generator=g) - 0.5
        nrm[2] += 2.0
        kw["normals"] = nrm / nrm.norm(dim=0, keepdim=True)
    if mask:
        m = torch.ones(1, h, w, dtype=torch.bool)
        m[0, :2, :2] = False
        kw["mask"] = m
    if saturated:
        sat = torch.zeros(n, 3, h, w, dtype=torch.bool)
        sat[0, 1, 2, 3] = True
        images[0, 1, 2, 3] = 1.0
        kw["saturated"] = sat
    return Capture(images=images, lights=lights, intensities=torch.full((n, 3), 0.5), cameras=cameras,
                   size=(0.1, 0.12), names=[f"images/{k:03d}.png" for k in range(n)], **kw)


def assert_same(a: Capture, b: Capture, names=True):
    for f in ("images", "normals", "mask", "lights", "intensities", "cameras", "saturated"):
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and torch.equal(x, y), f
    assert a.size == b.size
    if names:
        assert a.names == b.names


@pytest.fixture
def cap_dir(tmp_path):
    """A valid 8-bit linear capture directory (3 shots, 6x5) whose json the tests break."""
    return save_capture(make_capture(), tmp_path / "cap", bits=8)


def edit_json(path: Path, fn):
    f = path / "capture.json"
    meta = json.loads(f.read_text())
    fn(meta)
    f.write_text(json.dumps(meta))


def load_error(path, *words):
    with pytest.raises(CaptureError) as e:
        load_capture(path)
    one_line(e, *words)
    return str(e.value)


# ----------------------------------------------------------------------------------- round trip


class TestRoundTrip:
    @pytest.mark.parametrize("extras", [dict(), dict(normals=True, mask=True, saturated=True)])
    def test_npy_exact(self, tmp_path, extras):
        c = make_capture(**extras)
        save_capture(c, tmp_path / "a")  # default: float npy
        c1 = load_capture(tmp_path / "a")
        assert_same(c, c1, names=False)
        assert c1.names == ["images/000.npy", "images/001.npy", "images/002.npy"]
        save_capture(c1, tmp_path / "b")
        assert_same(c1, load_capture(tmp_path / "b"))

    @pytest.mark.parametrize("bits", [8, 16])
    @pytest.mark.parametrize("color_space", ["linear", "srgb"])
    def test_png_resave_exact(self, tmp_path, bits, color_space):
        c = make_capture(normals=True, mask=True)
        save_capture(c, tmp_path / "a", bits=bits, color_space=color_space)
        c1 = load_capture(tmp_path / "a")
        assert c1.color_space == color_space
        tol = 0.5 / (2**bits - 1) * (13 if color_space == "srgb" else 1.0001)
        assert float((c1.images - c.images).abs().max()) <= tol
        save_capture(c1, tmp_path / "b", bits=bits)  # same encoding it was loaded with
        c2 = load_capture(tmp_path / "b")
        assert_same(c1, c2)
        assert c2.color_space == color_space

    def test_16bit_to_npy_and_back_exact(self, tmp_path):
        save_capture(make_capture(saturated=True), tmp_path / "a", bits=16)
        c1 = load_capture(tmp_path / "a")
        save_capture(c1, tmp_path / "b")
        assert_same(c1, load_capture(tmp_path / "b"), names=False)

    def test_names_keep_source_stems(self, tmp_path):
        c = make_capture()
        c.names = ["images/000.png", "images/004.png", "images/shot_b.png"]
        save_capture(c, tmp_path / "a", bits=8)
        assert load_capture(tmp_path / "a").names == c.names
        c.names = ["a/x.png", "b/x.png", "c/y.png"]  # duplicate stems → NNN
        save_capture(c, tmp_path / "b", bits=8)
        assert load_capture(tmp_path / "b").names == ["images/000.png", "images/001.png", "images/002.png"]

    def test_optional_files_only_when_needed(self, tmp_path):
        save_capture(make_capture(), tmp_path / "flat")
        meta = json.loads((tmp_path / "flat" / "capture.json").read_text())
        assert "normals" not in meta and "mask" not in meta and "saturated" not in meta
        assert not (tmp_path / "flat" / "normals.npy").exists()
        save_capture(make_capture(normals=True, mask=True), tmp_path / "full", bits=8)
        meta = json.loads((tmp_path / "full" / "capture.json").read_text())
        assert meta["normals"] == "normals.npy" and meta["mask"] == "mask.png"
        assert np.load(tmp_path / "full" / "normals.npy").shape == (6, 5, 3)
        assert meta["format"] == "torchmetal-capture" and meta["version"] == 1 and len(meta["shots"]) == 3

    def test_load_from_json_path(self, cap_dir):
        assert load_capture(cap_dir / "capture.json").num_shots == 3

    def test_directional_lights(self, tmp_path):
        c = make_capture(directional=True)
        save_capture(c, tmp_path / "d")
        assert torch.equal(load_capture(tmp_path / "d").lights, c.lights)


class TestAtomicSave:
    def test_interrupted_save_keeps_old_capture(self, tmp_path, monkeypatch):
        path = save_capture(make_capture(seed=1), tmp_path / "cap")
        before = load_capture(path)
        import torchmetal.io.capture_save as cap_mod

        real = cap_mod.encode_image
        calls = []

        def flaky(*a, **k):
            calls.append(1)
            if len(calls) == 2:
                raise KeyboardInterrupt
            return real(*a, **k)

        monkeypatch.setattr(cap_mod, "encode_image", flaky)
        with pytest.raises(KeyboardInterrupt):
            save_capture(make_capture(seed=2), path)
        assert_same(before, load_capture(path))
        assert sorted(p.name for p in tmp_path.iterdir()) == ["cap"]

    def test_overwrites_existing_capture(self, tmp_path):
        save_capture(make_capture(seed=1), tmp_path / "cap")
        new = make_capture(seed=2, n=2)
        save_capture(new, tmp_path / "cap")
        assert_same(new, load_capture(tmp_path / "cap"), names=False)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["cap"]
        assert len(list((tmp_path / "cap" / "images").iterdir())) == 2

    def test_refuses_foreign_directory(self, tmp_path):
        (tmp_path / "docs").mkdir()
        (tmp_path / "docs" / "thesis.txt").write_text("precious")
        with pytest.raises(CaptureError) as e:
            save_capture(make_capture(), tmp_path / "docs")
        one_line(e, "expected an empty directory or an existing capture")
        assert (tmp_path / "docs" / "thesis.txt").read_text() == "precious"

    def test_bad_bits(self, tmp_path):
        with pytest.raises(CaptureError) as e:
            save_capture(make_capture(), tmp_path / "x", bits=12)
        one_line(e, "8, 16 or 'npy'", "12")
        assert not (tmp_path / "x").exists()
        assert list(tmp_path.iterdir()) == []


class TestDecoding:
    def test_srgb_decoded_to_linear(self, cap_dir):
        edit_json(cap_dir, lambda m: m.update(color_space="srgb"))
        lin = load_capture(cap_dir.with_name("cap"))
        raw = cv2.imread(str(cap_dir / "images" / "001.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
        # the sRGB curve in float64 on code / 255, rounded once to float32 (what the lookup table holds)
        expected = srgb_to_linear(torch.from_numpy(raw.astype(np.float64) / 255).permute(2, 0, 1)).float()
        assert torch.equal(lin.images[1], expected)
        assert lin.images.dtype == torch.float32 and lin.color_space == "srgb"

    @pytest.mark.parametrize("bits", [8, 16])
    def test_srgb_integer_files_decoded_by_table(self, tmp_path, bits, monkeypatch):
        import torchmetal.io.capture as capture_mod

        c = make_capture(n=2, h=16, w=20)
        c.color_space = "srgb"
        root = save_capture(c, tmp_path / "s", bits=bits)
        raws = [cv2.imread(str(root / n), cv2.IMREAD_UNCHANGED)[..., ::-1] for n in c.names]
        calls = []
        monkeypatch.setattr(capture_mod, "srgb_to_linear", lambda x: calls.append(x) or srgb_to_linear(x))
        lin = load_capture(root)
        assert not calls  # integer codes never go through the float formula
        table = code_table(bits, True)
        for k, raw in enumerate(raws):
            assert torch.equal(lin.images[k], torch.from_numpy(table[raw.transpose(2, 0, 1)]))

    def test_srgb_float_files_decoded_by_formula(self, tmp_path):
        root = save_capture(make_capture(n=2), tmp_path / "f", color_space="srgb")
        c = load_capture(root)
        for k, name in enumerate(c.names):
            stored = torch.from_numpy(np.load(root / name)).permute(2, 0, 1).contiguous()
            assert torch.equal(c.images[k], srgb_to_linear(stored))

    def test_saturation_8bit(self, tmp_path):
        c = make_capture()
        c.images[1, 2, 0, 0] = 1.0
        c.images[2, :, 3, 4] = 1.0
        save_capture(c, tmp_path / "s", bits=8)
        sat = load_capture(tmp_path / "s").saturated
        assert sat.dtype == torch.bool and int(sat.sum()) == 4
        assert bool(sat[1, 2, 0, 0]) and bool(sat[2, :, 3, 4].all())

    def test_saturation_16bit_raw_values(self, tmp_path):
        root = tmp_path / "raw"
        save_capture(make_capture(n=1), root, bits=16)
        img = np.full((6, 5, 3), 30000, np.uint16)
        img[0, 0, 0] = 65535
        img[5, 4, 2] = 65534
        cv2.imwrite(str(root / "images" / "000.png"), img[..., ::-1])
        c = load_capture(root)
        assert int(c.saturated.sum()) == 1 and bool(c.saturated[0, 0, 0, 0])

    def test_float_images_never_saturated(self, tmp_path):
        c = make_capture()
        c.images[0, 0, 0, 0] = 1.0
        save_capture(c, tmp_path / "f")
        assert not load_capture(tmp_path / "f").saturated.any()

    def test_float_images_may_exceed_one(self, tmp_path):
        c = make_capture()
        c.images[0] *= 5
        save_capture(c, tmp_path / "hdr")
        assert torch.equal(load_capture(tmp_path / "hdr").images, c.images)

    def test_non_unit_normals_normalised(self, cap_dir):
        n = np.zeros((6, 5, 3), np.float32)
        n[..., 2] = 2.0
        n[0, 0] = [3.0, 0.0, 4.0]
        np.save(cap_dir / "normals.npy", n)
        edit_json(cap_dir, lambda m: m.update(normals="normals.npy"))
        c = load_capture(cap_dir)
        assert torch.allclose(c.normals[:, 0, 0], torch.tensor([0.6, 0.0, 0.8]))
        assert torch.allclose(c.normals.norm(dim=0), torch.ones(6, 5))

    def test_mask_nonzero_is_sample(self, cap_dir):
        m = np.zeros((6, 5), np.uint8)
        m[1:, :] = 7
        cv2.imwrite(str(cap_dir / "mask.png"), m)
        edit_json(cap_dir, lambda meta: meta.update(mask="mask.png"))
        c = load_capture(cap_dir)
        assert c.mask.shape == (1, 6, 5) and c.mask.dtype == torch.bool and int(c.mask.sum()) == 25

    def test_preallocated_float32(self, cap_dir):
        c = load_capture(cap_dir)
        assert c.images.dtype == torch.float32 and c.images.is_contiguous()
        for t in (c.lights, c.intensities, c.cameras, c.normals):
            assert t.dtype == torch.float32


# ------------------------------------------------------------------------------ bad directories


class TestBadCaptureFiles:
    def test_json_missing(self, tmp_path):
        (tmp_path / "empty").mkdir()
        load_error(tmp_path / "empty", "capture.json", "expected a capture description file", "found nothing")

    def test_malformed_json(self, cap_dir):
        (cap_dir / "capture.json").write_text('{\n "format": "torchmetal-capture",\n "version" 1\n}')
        load_error(cap_dir, "expected valid JSON", "line 3 column 12")

    def test_json_not_object(self, cap_dir):
        (cap_dir / "capture.json").write_text("[1, 2]")
        load_error(cap_dir, "expected a JSON object", "list")

    def test_missing_image(self, cap_dir):
        (cap_dir / "images" / "001.png").unlink()
        load_error(cap_dir, "001.png", "expected an image file", "found nothing")

    def test_unreadable_image(self, cap_dir):
        (cap_dir / "images" / "002.png").write_bytes(b"\x89PNG broken")
        load_error(cap_dir, "002.png", "expected a readable PNG")

    def test_images_of_different_sizes(self, cap_dir):
        write_image(cap_dir / "images" / "001.png", np.zeros((6, 4, 3), np.float32))
        load_error(cap_dir, "001.png", "expected size 5x6", "found 4x6")

    def test_wrong_channel_count(self, cap_dir):
        cv2.imwrite(str(cap_dir / "images" / "002.png"), np.zeros((6, 5), np.uint8))
        load_error(cap_dir, "002.png", "expected 3", "found 1")

    @pytest.mark.parametrize("bad", [float("nan"), float("inf")])
    def test_non_finite_pixels(self, cap_dir, bad):
        img = np.full((6, 5, 3), 0.5, np.float32)
        img[2, 2, 1] = bad
        np.save(cap_dir / "images" / "bad.npy", img)
        edit_json(cap_dir, lambda m: m["shots"][1].update(image="images/bad.npy"))
        load_error(cap_dir, "bad.npy", "expected finite pixel values", "NaN" if math.isnan(bad) else "Inf")

    def test_negative_pixels(self, cap_dir):
        img = np.full((6, 5, 3), 0.5, np.float32)
        img[0, 1, 2] = -0.25
        np.save(cap_dir / "images" / "neg.npy", img)
        edit_json(cap_dir, lambda m: m["shots"][0].update(image="images/neg.npy"))
        load_error(cap_dir, "neg.npy", "expected pixel values >= 0", "-0.25")

    def test_normals_missing_file(self, cap_dir):
        edit_json(cap_dir, lambda m: m.update(normals="normals.npy"))
        load_error(cap_dir, "normals.npy", "found nothing")

    def test_normals_wrong_shape(self, cap_dir):
        np.save(cap_dir / "normals.npy", np.ones((5, 6, 3), np.float32))
        edit_json(cap_dir, lambda m: m.update(normals="normals.npy"))
        load_error(cap_dir, "normals.npy", "expected shape (H, W, 3) = (6, 5, 3)", "found (5, 6, 3)")

    def test_normals_non_finite(self, cap_dir):
        n = np.zeros((6, 5, 3), np.float32)
        n[..., 2] = 1
        n[3, 1, 0] = np.nan
        np.save(cap_dir / "normals.npy", n)
        edit_json(cap_dir, lambda m: m.update(normals="normals.npy"))
        load_error(cap_dir, "expected finite normals", "row 3, col 1")

    def test_normals_zero_length(self, cap_dir):
        n = np.zeros((6, 5, 3), np.float32)
        n[..., 2] = 1
        n[4, 2] = 0
        np.save(cap_dir / "normals.npy", n)
        edit_json(cap_dir, lambda m: m.update(normals="normals.npy"))
        load_error(cap_dir, "expected non-zero normals", "1 zero-length", "row 4, col 2")

    def test_mask_wrong_size(self, cap_dir):
        cv2.imwrite(str(cap_dir / "mask.png"), np.full((5, 5), 255, np.uint8))
        edit_json(cap_dir, lambda m: m.update(mask="mask.png"))
        load_error(cap_dir, "mask.png", "expected a mask of size 5x6", "found shape (5, 5)")

    def test_mask_empty(self, cap_dir):
        # no pixel on the sample: a clear error at load (it had reached the fit and died writing an inf to JSON)
        cv2.imwrite(str(cap_dir / "mask.png"), np.zeros((6, 5), np.uint8))
        edit_json(cap_dir, lambda m: m.update(mask="mask.png"))
        load_error(cap_dir, "Capture.mask", "expected at least one pixel on the sample", "found none")

    def test_mask_unreadable(self, cap_dir):
        (cap_dir / "mask.png").write_bytes(b"nope")
        edit_json(cap_dir, lambda m: m.update(mask="mask.png"))
        load_error(cap_dir, "mask.png", "expected a readable mask image")


def _shot(k, key, value):
    return lambda m: m["shots"][k].__setitem__(key, value)


BAD_JSON = {
    "wrong_format": (lambda m: m.update(format="torchmetal-material"), ["expected format 'torchmetal-capture'", "torchmetal-material"]),
    "no_format": (lambda m: m.pop("format"), ["expected \"format\"", "no format key"]),
    "unsupported_version": (lambda m: m.update(version=2), ["expected version 1", "found 2"]),
    "missing_top_key": (lambda m: m.pop("surface"), ["expected keys", "missing ['surface']"]),
    "missing_color_space": (lambda m: m.pop("color_space"), ["missing ['color_space']"]),
    "missing_shot_key": (lambda m: m["shots"][1].pop("camera"), ["shots[1]", "missing ['camera']"]),
    "empty_shots": (lambda m: m.update(shots=[]), ["expected at least 1 shot", "found 0"]),
    "shots_not_list": (lambda m: m.update(shots={"a": 1}), ["expected a list of shots", "dict"]),
    "bad_color_space": (lambda m: m.update(color_space="adobe"), ["expected one of ['srgb', 'linear']", "adobe"]),
    "image_not_string": (_shot(0, "image", 3), ["shots[0].image", "expected a file name"]),
    "light_length": (_shot(1, "light", [0, 0, 1]), ["shots[1].light", "expected 4 numbers", "found 3 values"]),
    "light_non_finite": (_shot(0, "light", [0, 0, float("nan"), 1]), ["shots[0].light", "expected finite numbers"]),
    "light_not_numbers": (_shot(0, "light", [0, "a", 1, 1]), ["shots[0].light", "expected 4 numbers"]),
    "light_bad_w": (_shot(2, "light", [0, 0, 1, 0.5]), ["shots[2].light", "w = 1 (point light) or w = 0", "found w = 0.5"]),
    "point_light_below": (_shot(0, "light", [0, 0, -0.1, 1]), ["shots[0].light", "expected z > 0", "point light above the surface plane", "found z = -0.1"]),
    "point_light_on_plane": (_shot(0, "light", [0.2, 0, 0, 1]), ["expected z > 0", "found z = 0"]),
    "directional_below_horizon": (_shot(1, "light", [1, 0, -0.2, 0]), ["shots[1].light", "above the horizon", "found z = -0.2"]),
    "camera_length": (_shot(0, "camera", [0, 0, 1, 1, 1]), ["shots[0].camera", "expected 4 numbers", "found 5 values"]),
    "camera_non_finite": (_shot(0, "camera", [0, float("inf"), 1, 1]), ["shots[0].camera", "expected finite numbers"]),
    "camera_bad_w": (_shot(0, "camera", [0, 0, 1, 2]), ["shots[0].camera", "found w = 2"]),
    "camera_below": (_shot(2, "camera", [0, 0, -1, 1]), ["shots[2].camera", "expected z > 0 (camera above the surface)", "found z = -1"]),
    "camera_orthographic_below": (_shot(2, "camera", [0, 0, -1, 0]), ["shots[2].camera", "expected z > 0"]),
    "intensity_length": (_shot(0, "light_intensity", [1, 1]), ["shots[0].light_intensity", "expected 3 numbers", "found 2 values"]),
    "intensity_negative": (_shot(1, "light_intensity", [1, -1, 1]), ["shots[1].light_intensity", "expected values >= 0"]),
    "intensity_non_finite": (_shot(1, "light_intensity", [1, float("inf"), 1]), ["shots[1].light_intensity", "expected finite"]),
    "surface_zero_width": (lambda m: m["surface"].update(width=0), ["surface width/height", "expected positive finite"]),
    "surface_negative_height": (lambda m: m["surface"].update(height=-2), ["expected positive finite", "-2"]),
    "surface_not_object": (lambda m: m.update(surface=[1, 1]), ["surface: expected {\"width\": w, \"height\": h}"]),
    "normals_not_string": (lambda m: m.update(normals=5), ["normals: expected a file name or null"]),
    # found by the fuzz suite (tests/fuzz): integers beyond the float range (JSON literals of 309+ digits) raised OverflowError
    "light_huge_integer": (_shot(0, "light", [10 ** 400, 0, 1, 1]), ["shots[0].light", "expected finite numbers", "inf"]),
    "surface_huge_integer": (lambda m: m["surface"].update(height=10 ** 400), ["surface width/height", "expected positive finite"]),
    "camera_beyond_float32": (_shot(1, "camera", [0, 1e39, 1, 1]), ["shots[1].camera", "within the float32 range"]),
    "light_below_float32_resolution": (_shot(1, "light", [0, 0, 1e-300, 1]), ["shots[1]", "expected z > 0", "found z = 0"]),
    # found by the fuzz suite: a light 2e9 away for a photo of normal brightness overflowed the fit (inf in material.json)
    "light_too_far_for_photo": (_shot(0, "light", [2.1e9, 0, 0.3, 1]), ["shots[0] (images/000.png)", "irradiance", "too far or too weak"]),
}


@pytest.mark.parametrize("case", sorted(BAD_JSON))
def test_bad_capture_json(cap_dir, case):
    mutate, words = BAD_JSON[case]
    edit_json(cap_dir, mutate)
    load_error(cap_dir, "capture.json", *words)


# ------------------------------------------------------------------------ Capture built in Python


def _with(**changes):
    def build():
        c = make_capture()
        kw = dict(images=c.images, normals=c.normals, mask=c.mask, lights=c.lights, intensities=c.intensities,
                  cameras=c.cameras, size=c.size, saturated=c.saturated, names=c.names, color_space=c.color_space)
        for k, v in changes.items():
            kw[k] = v(kw[k]) if callable(v) else v
        return Capture(**kw)
    return build


def _set(index, value):
    def f(t):
        t = t.clone()
        t[index] = value
        return t
    return f


BAD_CAPTURE = {
    "images_3d": (_with(images=torch.rand(3, 6, 5)), ["Capture.images", "(N, 3, H, W)", "found (3, 6, 5)"]),
    "images_4_channels": (_with(images=torch.rand(3, 4, 6, 5)), ["Capture.images", "found (3, 4, 6, 5)"]),
    "images_int": (_with(images=torch.zeros(3, 3, 6, 5, dtype=torch.uint8)), ["floating-point", "uint8"]),
    "images_nan": (_with(images=_set((0, 0, 0, 0), float("nan"))), ["Capture.images", "expected finite", "NaN"]),
    "images_negative": (_with(images=_set((1, 2, 3, 4), -1.0)), ["Capture.images", "expected pixel values >= 0"]),
    "normals_shape": (_with(normals=torch.ones(3, 5, 6)), ["Capture.normals", "(3, 6, 5)", "found (3, 5, 6)"]),
    "normals_not_unit": (_with(normals=lambda n: n * 2), ["Capture.normals", "expected unit vectors"]),
    "normals_nan": (_with(normals=_set((0, 0, 0), float("nan"))), ["Capture.normals", "NaN"]),
    "mask_dtype": (_with(mask=torch.ones(1, 6, 5)), ["Capture.mask", "torch.bool"]),
    "mask_shape": (_with(mask=torch.ones(6, 5, dtype=torch.bool)), ["Capture.mask", "(1, 6, 5)"]),
    "lights_shape": (_with(lights=torch.ones(3, 3)), ["Capture.lights", "(3, 4)", "found (3, 3)"]),
    "lights_count": (_with(lights=torch.ones(2, 4)), ["Capture.lights", "(3, 4)", "found (2, 4)"]),
    "light_below": (_with(lights=_set((1, 2), -0.5)), ["shot 1", "light", "expected z > 0", "-0.5"]),
    "light_bad_w": (_with(lights=_set((0, 3), 0.3)), ["shot 0", "w = 1 (point light) or w = 0"]),
    "light_inf": (_with(lights=_set((0, 0), float("inf"))), ["shot 0", "expected finite numbers"]),
    "intensity_negative": (_with(intensities=_set((2, 1), -1.0)), ["shot 2", "light_intensity", "expected values >= 0"]),
    "intensity_shape": (_with(intensities=torch.ones(3, 4)), ["Capture.intensities", "(3, 3)"]),
    "camera_below": (_with(cameras=_set((0, 2), 0.0)), ["shot 0", "camera", "expected z > 0"]),
    "saturated_dtype": (_with(saturated=torch.zeros(3, 3, 6, 5)), ["Capture.saturated", "torch.bool"]),
    "names_count": (_with(names=["a.png"]), ["Capture.names", "expected 3", "found 1"]),
    "color_space": (_with(color_space="rgb"), ["Capture.color_space", "rgb"]),
    "size_negative": (_with(size=(0.1, -1.0)), ["Capture.size", "expected positive finite (width, height)"]),
    "size_length": (_with(size=(0.1,)), ["Capture.size"]),
    "images_no_pixels": (_with(images=torch.rand(3, 3, 0, 0)), ["Capture.images", "expected at least 1x1 pixels", "found 0x0"]),
    "intensity_too_weak": (_with(intensities=torch.full((3, 3), 1e-20)), ["shot 0", "irradiance", "too far or too weak"]),
}


@pytest.mark.parametrize("case", sorted(BAD_CAPTURE))
def test_bad_capture_in_python(case):
    build, words = BAD_CAPTURE[case]
    with pytest.raises(CaptureError) as e:
        build()
    one_line(e, *words)


def test_normals_near_float64_limit_are_normalised(cap_dir):
    """Found by the fuzz suite (tests/fuzz): |n|² overflowed (a RuntimeWarning on stderr beside the result)."""
    n = np.zeros((6, 5, 3))
    n[..., 2] = 1e200
    n[0, 0] = [1e200, 0, 1e200]
    np.save(cap_dir / "normals.npy", n)
    edit_json(cap_dir, lambda m: m.update(normals="normals.npy"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        c = load_capture(cap_dir)
    assert torch.allclose(c.normals[:, 0, 0], torch.tensor([0.5 ** 0.5, 0, 0.5 ** 0.5]))
    assert torch.equal(c.normals[:, 1:, :], torch.tensor([0.0, 0, 1]).view(3, 1, 1).expand(3, 5, 5))


def test_dark_shots_are_not_exposure_checked():
    """A zero intensity or an all-black photo says nothing about the light's distance."""
    c = make_capture()
    Capture(images=torch.zeros_like(c.images), lights=c.lights, intensities=torch.full((3, 3), 1e-30), cameras=c.cameras,
            size=c.size)
    Capture(images=c.images, lights=c.lights, intensities=torch.zeros(3, 3), cameras=c.cameras, size=c.size)


class TestCaptureObject:
    def test_defaults(self):
        c = Capture(images=torch.rand(2, 3, 4, 5), lights=torch.tensor([[0, 0, 1, 1.0], [0, 0, 1, 0.0]]),
                    intensities=torch.ones(2, 3), cameras=torch.tensor([[0, 0, 1, 1.0]] * 2), size=(1, 2))
        assert c.num_shots == 2 and c.height == 4 and c.width == 5 and c.size == (1.0, 2.0)
        assert c.flat and c.mask.all() and c.mask.shape == (1, 4, 5) and not c.saturated.any()
        assert c.names == ["images/000.png", "images/001.png"] and c.color_space == "linear"
        assert "2 shots" in repr(c) and "4x5" in repr(c)

    def test_subset(self):
        c = make_capture(n=4, saturated=True)
        s = c.subset([2, 0])
        assert s.num_shots == 2 and s.names == [c.names[2], c.names[0]]
        assert torch.equal(s.images, c.images[[2, 0]]) and torch.equal(s.lights, c.lights[[2, 0]])
        assert torch.equal(s.saturated, c.saturated[[2, 0]]) and torch.equal(s.normals, c.normals)
        assert c.subset(slice(1, 3)).names == c.names[1:3]
        assert torch.equal(c.subset(torch.tensor([-1])).images, c.images[-1:])
        with pytest.raises(CaptureError) as e:
            c.subset([4])
        one_line(e, "[0, 4)")
        with pytest.raises(CaptureError) as e:
            c.subset([])
        one_line(e, "at least one shot")

    def test_to(self):
        c = make_capture(mask=True)
        d = c.to(dtype=torch.float64)
        assert d.images.dtype == torch.float64 and d.lights.dtype == torch.float64 and d.mask.dtype == torch.bool
        assert torch.equal(d.images.float(), c.images)
        e = c.to("cpu")
        assert e.images.device.type == "cpu" and torch.equal(e.images, c.images)


class TestCheckLightCamera:
    light = torch.tensor([[0.1, 0.0, 0.3, 1.0], [0.0, 0.5, 0.5, 0.0]])
    inten = torch.ones(2, 3)
    cam = torch.tensor([[0.0, 0.0, 0.3, 1.0], [0.0, 0.0, 1.0, 0.0]])

    def test_good(self):
        check_light_camera(self.light, self.inten, self.cam)

    @pytest.mark.parametrize("case,args,words", [
        ("shape", lambda s: (s.light[:, :3], s.inten, s.cam), ["light: expected shape (B, 4)", "(2, 3)"]),
        ("batch", lambda s: (s.light, s.inten[:1], s.cam), ["same batch size", "2, 1, 2"]),
        ("below", lambda s: (s.light * torch.tensor([1, 1, -1, 1.0]), s.inten, s.cam), ["shot 0: light", "expected z > 0"]),
        ("w", lambda s: (s.light, s.inten, s.cam + torch.tensor([0, 0, 0, 0.5])), ["shot 0: camera", "found w = 1.5"]),
        ("negative", lambda s: (s.light, -s.inten, s.cam), ["shot 0: light_intensity", "expected values >= 0"]),
        ("int", lambda s: (s.light.long(), s.inten, s.cam), ["light: expected a floating-point tensor"]),
    ])
    def test_bad(self, case, args, words):
        with pytest.raises(InputError) as e:
            check_light_camera(*args(self))
        one_line(e, *words)

    def test_error_class_selectable(self):
        with pytest.raises(CaptureError):
            check_light_camera(self.light, -self.inten, self.cam, error=CaptureError)


# ----------------------------------------------------------------------------------- real data


def _real(name):
    path = DATA / name
    if not (path / "capture.json").is_file():
        pytest.skip(f"shared data {name} not present at {path}")
    return load_capture(path)


def test_real_cards_blue():
    c = _real("cards_blue")
    assert c.images.shape == (7, 3, 1024, 1024) and c.images.dtype == torch.float32
    assert c.color_space == "srgb" and c.flat and bool(c.mask.all())
    assert c.size == pytest.approx((6.848, 6.848))
    assert (c.lights[:, 3] == 1).all() and (c.cameras[:, 3] == 1).all()
    frac = float(c.saturated.float().mean())
    assert 0.001 < frac < 0.05  # ~1-2% clipped foil highlights
    assert torch.equal(c.images[c.saturated], torch.ones(int(c.saturated.sum())))
    assert float(c.images.min()) >= 0 and float(c.images.max()) <= 1
    assert c.names[3] == "images/004.png"


def test_real_uw_gray_sphere():
    c = _real("uw_gray_sphere")
    assert c.images.shape == (12, 3, 224, 224)
    assert c.color_space == "linear" and not c.flat
    assert c.mask.shape == (1, 224, 224) and 0.5 < float(c.mask.float().mean()) < 0.9
    assert torch.allclose(c.normals.norm(dim=0), torch.ones(224, 224), atol=1e-5)
    assert (c.lights[:, 3] == 0).all() and torch.equal(c.cameras[0], torch.tensor([0.0, 0.0, 1.0, 0.0]))
    centre = c.normals[:, 112, 112]
    assert float(centre[2]) > 0.99
