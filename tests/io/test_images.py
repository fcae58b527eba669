"""sRGB transfer function and image files: exactness, channel order, saturation, one-line errors."""

import os
import sys

import cv2
import numpy as np
import pytest
import torch

from torchmetal.errors import CaptureError, InputError
from torchmetal.io.images import (
    code_table,
    decode_planes,
    linear_to_srgb,
    quantize,
    read_image,
    read_raw,
    srgb_to_linear,
    write_image,
)


def one_line(exc_info, *words):
    msg = str(exc_info.value)
    assert "\n" not in msg and msg
    for w in words:
        assert w in msg, (w, msg)


def ref_decode(x):
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4)


def ref_encode(x):
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055)


class TestSrgb:
    x = np.linspace(-0.1, 1.5, 4001)

    def test_decode_matches_float64_reference(self):
        got = srgb_to_linear(torch.tensor(self.x, dtype=torch.float64)).numpy()
        np.testing.assert_allclose(got, ref_decode(self.x), rtol=1e-14, atol=1e-16)

    def test_encode_matches_float64_reference(self):
        got = linear_to_srgb(torch.tensor(self.x, dtype=torch.float64)).numpy()
        np.testing.assert_allclose(got, ref_encode(self.x), rtol=1e-14, atol=1e-16)

    def test_float32_close_to_reference(self):
        got = srgb_to_linear(torch.tensor(self.x, dtype=torch.float32)).double().numpy()
        np.testing.assert_allclose(got, ref_decode(self.x.astype(np.float32)), rtol=2e-6, atol=1e-8)
        got = linear_to_srgb(torch.tensor(self.x, dtype=torch.float32)).double().numpy()
        np.testing.assert_allclose(got, ref_encode(self.x.astype(np.float32)), rtol=2e-6, atol=1e-8)

    def test_reference_points(self):
        v = torch.tensor([0.0, 0.04045, 0.5, 1.0], dtype=torch.float64)
        np.testing.assert_allclose(srgb_to_linear(v).numpy(), [0.0, 0.04045 / 12.92, 0.21404114048223255, 1.0], rtol=1e-14)
        np.testing.assert_allclose(linear_to_srgb(torch.tensor([0.0031308, 1.0], dtype=torch.float64)).numpy(),
                                   [0.0031308 * 12.92, 1.0], rtol=1e-14)

    def test_round_trip_every_8bit_level(self):
        v = torch.arange(256, dtype=torch.float32) / 255
        back = torch.round(linear_to_srgb(srgb_to_linear(v)) * 255)
        assert torch.equal(back, torch.arange(256, dtype=torch.float32))

    def test_any_shape_dtype_preserved(self):
        for dtype in (torch.float32, torch.float64, torch.float16):
            x = torch.rand(2, 1, 3, 4, 5).to(dtype)
            for f in (srgb_to_linear, linear_to_srgb):
                y = f(x)
                assert y.shape == x.shape and y.dtype == dtype and y.device == x.device

    def test_gradcheck(self):
        x = torch.tensor([0.001, 0.02, 0.3, 0.9, 1.2], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(srgb_to_linear, (x,))
        assert torch.autograd.gradcheck(linear_to_srgb, (x,))

    def test_gradient_finite_at_zero_and_negative(self):
        x = torch.tensor([-0.5, 0.0, 0.04045, 0.0031308], requires_grad=True)
        (srgb_to_linear(x).sum() + linear_to_srgb(x).sum()).backward()
        assert torch.isfinite(x.grad).all()


class TestCodeTables:
    """Integer files are decoded by lookup table; the tables are the formula, exactly."""

    @pytest.mark.parametrize("bits", [8, 16])
    def test_srgb_table_is_float64_formula_cast_once(self, bits):
        top = 2**bits - 1
        table = code_table(bits, True)
        assert table.dtype == np.float32 and table.shape == (top + 1,) and not table.flags.writeable
        codes = np.arange(top + 1, dtype=np.float64) / top
        np.testing.assert_array_equal(table, srgb_to_linear(torch.from_numpy(codes)).numpy().astype(np.float32))
        np.testing.assert_array_equal(table, ref_decode(codes).astype(np.float32))  # independent reference
        assert table[0] == 0.0 and table[-1] == 1.0 and (np.diff(table) > 0).all()

    @pytest.mark.parametrize("bits", [8, 16])
    def test_linear_table_is_correctly_rounded_division(self, bits):
        top = 2**bits - 1
        table = code_table(bits, False)
        np.testing.assert_array_equal(table, np.arange(top + 1, dtype=np.float32) / np.float32(top))
        np.testing.assert_array_equal(table, (np.arange(top + 1, dtype=np.float64) / top).astype(np.float32))

    def test_tables_built_once(self):
        assert code_table(16, True) is code_table(16, True)
        with pytest.raises(InputError):
            code_table(12, True)

    @pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
    @pytest.mark.parametrize("srgb", [False, True])
    def test_decode_planes_integer_codes_every_value(self, dtype, srgb):
        bits = 8 if dtype == np.uint8 else 16
        top = 2**bits - 1
        codes = np.arange(top + 1, dtype=dtype)
        rng = np.random.default_rng(3)
        bgra = rng.permutation(np.concatenate([codes] * 4)).reshape(-1, 4, 1, 4)[:, :, 0, :].reshape(-1, 16, 4)
        raw = bgra[:, :, [2, 1, 0]]  # a strided RGB view of BGR(A) data, as read_raw returns
        out, sat = np.full((3, *raw.shape[:2]), np.nan, np.float32), np.empty((3, *raw.shape[:2]), bool)
        decode_planes(raw, out, sat, srgb=srgb)
        planes = raw.transpose(2, 0, 1).astype(np.float64) / top
        want = ref_decode(planes) if srgb else planes
        np.testing.assert_array_equal(out, want.astype(np.float32))
        np.testing.assert_array_equal(sat, raw.transpose(2, 0, 1) == top)

    def test_decode_planes_no_full_size_temporaries(self):
        import tracemalloc

        raw = np.random.default_rng(5).integers(0, 65536, (501, 700, 3), dtype=np.uint16)[:, :, ::-1]
        out, sat = np.empty((3, 501, 700), np.float32), np.empty((3, 501, 700), bool)
        code_table(16, True)  # built outside the measurement
        tracemalloc.start()
        decode_planes(raw, out, sat, srgb=True)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert peak < out.nbytes / 4, peak  # one (3, H, W) intp index copy would be 2x out
        np.testing.assert_array_equal(out, code_table(16, True)[raw.transpose(2, 0, 1)])

    def test_decode_planes_other_out_dtype(self):
        raw = np.arange(256, dtype=np.uint8).reshape(16, 16, 1).repeat(3, axis=2)
        out, sat = np.empty((3, 16, 16), np.float64), np.empty((3, 16, 16), bool)
        decode_planes(raw, out, sat, srgb=True)
        np.testing.assert_array_equal(out, code_table(8, True)[raw.transpose(2, 0, 1)].astype(np.float64))

    def test_decode_planes_float_srgb_uses_formula(self):
        raw = np.random.default_rng(4).random((5, 6, 3)).astype(np.float32) * 1.2
        out, sat = np.empty((3, 5, 6), np.float32), np.empty((3, 5, 6), bool)
        decode_planes(raw, out, sat, srgb=True)
        expected = srgb_to_linear(torch.from_numpy(np.ascontiguousarray(raw.transpose(2, 0, 1)))).numpy()
        np.testing.assert_array_equal(out, expected)
        assert not sat.any()

    @pytest.mark.parametrize("bits", [8, 16])
    def test_srgb_file_round_trip_recovers_every_code(self, tmp_path, bits):
        """linear → sRGB encode → PNG file → load (table) → encode again: the same codes."""
        top = 2**bits - 1
        codes = np.arange(top + 1, dtype=np.int64)
        lin = code_table(bits, True).astype(np.float64)
        img = np.stack([lin, lin[::-1], np.roll(lin, 7)], axis=-1).reshape(-1, 256, 3)
        want = np.stack([codes, codes[::-1], np.roll(codes, 7)], axis=-1).reshape(-1, 256, 3)
        enc = linear_to_srgb(torch.from_numpy(img)).numpy()
        write_image(tmp_path / "a.png", enc, bits=bits)
        raw = read_raw(tmp_path / "a.png")
        np.testing.assert_array_equal(raw, want)
        out, sat = np.empty((3, *raw.shape[:2]), np.float32), np.empty((3, *raw.shape[:2]), bool)
        decode_planes(raw, out, sat, srgb=True)
        np.testing.assert_array_equal(out, img.transpose(2, 0, 1).astype(np.float32))
        back = linear_to_srgb(torch.from_numpy(out.astype(np.float64))).numpy().transpose(1, 2, 0)
        np.testing.assert_array_equal(quantize(back, bits), want)


def rand_image(h=7, w=5, seed=0):
    return np.random.default_rng(seed).random((h, w, 3)).astype(np.float32)


class TestFiles:
    @pytest.mark.parametrize("bits", [8, 16])
    def test_png_round_trip_exact(self, tmp_path, bits):
        top = 2**bits - 1
        img = rand_image()
        write_image(tmp_path / "a.png", img, bits=bits)
        back, sat = read_image(tmp_path / "a.png")
        assert back.dtype == np.float32 and back.shape == (7, 5, 3) and back.flags.c_contiguous
        np.testing.assert_array_equal(back, np.rint(img.astype(np.float64) * top).astype(np.float32) / np.float32(top))
        write_image(tmp_path / "b.png", back, bits=bits)  # re-encoding a loaded image is exact
        again, _ = read_image(tmp_path / "b.png")
        np.testing.assert_array_equal(again, back)
        raw = cv2.imread(str(tmp_path / "a.png"), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == (np.uint8 if bits == 8 else np.uint16)

    def test_read_raw_and_decode_planes(self, tmp_path):
        img = rand_image(h=9, w=4)
        write_image(tmp_path / "a.png", img, bits=16)
        raw = read_raw(tmp_path / "a.png")
        assert raw.dtype == np.uint16 and raw.shape == (9, 4, 3)
        out, sat = np.empty((3, 9, 4), np.float32), np.empty((3, 9, 4), bool)
        decode_planes(raw, out, sat)
        ref, ref_sat = read_image(tmp_path / "a.png")
        np.testing.assert_array_equal(out, ref.transpose(2, 0, 1))
        np.testing.assert_array_equal(sat, ref_sat.transpose(2, 0, 1))
        np.testing.assert_array_equal(out, raw.transpose(2, 0, 1).astype(np.float32) / np.float32(65535))

    def test_channel_order_rgb(self, tmp_path):
        bgr = np.zeros((2, 2, 3), np.uint8)
        bgr[..., 2] = 255  # red in OpenCV's BGR order
        cv2.imwrite(str(tmp_path / "red.png"), bgr)
        img, _ = read_image(tmp_path / "red.png")
        assert img[0, 0].tolist() == [1.0, 0.0, 0.0]
        write_image(tmp_path / "w.png", np.array([[[0.0, 0.0, 1.0]]], np.float32))  # blue
        assert cv2.imread(str(tmp_path / "w.png"))[0, 0].tolist() == [255, 0, 0]

    def test_rgba_png_drops_alpha(self, tmp_path):
        bgra = np.zeros((3, 4, 4), np.uint16)
        bgra[..., 1] = 1000
        bgra[..., 3] = 65535
        cv2.imwrite(str(tmp_path / "a.png"), bgra)
        img, sat = read_image(tmp_path / "a.png")
        assert img.shape == (3, 4, 3) and not sat.any()
        assert np.allclose(img[..., 1], 1000 / 65535) and (img[..., [0, 2]] == 0).all()

    def test_npy_round_trip_exact(self, tmp_path):
        img = rand_image() * 3  # float files may exceed 1
        write_image(tmp_path / "a.npy", img)
        back, sat = read_image(tmp_path / "a.npy")
        np.testing.assert_array_equal(back, img)
        assert back.dtype == np.float32 and not sat.any()

    def test_npy_float64_and_alpha(self, tmp_path):
        img = np.random.default_rng(1).random((4, 4, 4))
        np.save(tmp_path / "a.npy", img)
        back, _ = read_image(tmp_path / "a.npy")
        np.testing.assert_array_equal(back, img[..., :3].astype(np.float32))

    @pytest.mark.parametrize("bits", [8, 16])
    def test_saturation_from_raw_values(self, tmp_path, bits):
        img = np.full((2, 3, 3), 0.5, np.float32)
        img[0, 0, 1] = 1.0
        img[1, 2, :] = 7.0  # clipped on write → saturated
        write_image(tmp_path / "s.png", img, bits=bits)
        _, sat = read_image(tmp_path / "s.png")
        expected = np.zeros_like(sat)
        expected[0, 0, 1] = True
        expected[1, 2, :] = True
        np.testing.assert_array_equal(sat, expected)

    def test_write_clips_and_rounds(self, tmp_path):
        img = np.array([[[-0.2, 0.5, 1.3], [0.2 / 255, 0.6 / 255, 254.5 / 255]]], np.float32)
        write_image(tmp_path / "c.png", img)
        raw = cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED)[..., ::-1]
        assert raw.tolist() == [[[0, 128, 255], [0, 1, 254]]]

    def test_write_is_atomic(self, tmp_path, monkeypatch):
        write_image(tmp_path / "a.png", rand_image())
        before = (tmp_path / "a.png").read_bytes()

        def boom(*a, **k):
            raise KeyboardInterrupt

        monkeypatch.setattr(os, "replace", boom)
        with pytest.raises(KeyboardInterrupt):
            write_image(tmp_path / "a.png", rand_image(seed=1))
        assert (tmp_path / "a.png").read_bytes() == before
        assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]

    def test_write_creates_parent(self, tmp_path):
        write_image(tmp_path / "x" / "y" / "a.png", rand_image(), bits=16)
        assert (tmp_path / "x" / "y" / "a.png").is_file()


class TestBadFiles:
    def test_missing(self, tmp_path):
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "nope.png")
        one_line(e, "nope.png", "expected an image file")

    def test_undecodable(self, tmp_path):
        (tmp_path / "bad.png").write_bytes(b"not a png at all")
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "bad.png")
        one_line(e, "bad.png", "expected a readable PNG")

    def test_empty_file(self, tmp_path):
        (tmp_path / "empty.png").write_bytes(b"")
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "empty.png")
        one_line(e, "empty.png")

    @pytest.mark.parametrize("shape", [(0, 0, 3), (0, 4, 3), (5, 0, 3)])
    def test_no_pixels_rejected(self, tmp_path, shape):
        """Found by the fuzz suite (tests/fuzz): a 0x0 float image reached Capture.validate and raised a torch RuntimeError."""
        np.save(tmp_path / "none.npy", np.zeros(shape, np.float32))
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "none.npy")
        one_line(e, "none.npy", "expected an image of at least 1x1 pixels", f"found {shape[1]}x{shape[0]}")

    def test_grayscale_rejected(self, tmp_path):
        cv2.imwrite(str(tmp_path / "g.png"), np.zeros((4, 4), np.uint8))
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "g.png")
        one_line(e, "expected 3", "found 1")

    def test_two_channels_rejected(self, tmp_path):
        np.save(tmp_path / "two.npy", np.zeros((4, 4, 2), np.float32))
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "two.npy")
        one_line(e, "expected 3", "found 2")

    def test_five_channels_rejected(self, tmp_path):
        np.save(tmp_path / "five.npy", np.zeros((4, 4, 5), np.float32))
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "five.npy")
        one_line(e, "expected 3", "found 5")

    def test_bad_npy(self, tmp_path):
        (tmp_path / "x.npy").write_bytes(b"garbage")
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "x.npy")
        one_line(e, "expected a numpy .npy")

    def test_unknown_suffix(self, tmp_path):
        (tmp_path / "x.gif").write_bytes(b"GIF89a")
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "x.gif")
        one_line(e, ".gif", "expected a .png, .npy or .exr")

    def test_integer_npy_of_other_dtype(self, tmp_path):
        np.save(tmp_path / "i.npy", np.zeros((2, 2, 3), np.int32))
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "i.npy")
        one_line(e, "int32")

    def test_exr_unsupported_is_clear(self, tmp_path, monkeypatch):
        """Neither OpenCV nor the OpenEXR package reads EXR: one line that says what to do."""
        import torchmetal.io.images as images

        monkeypatch.setattr(images, "have_exr", lambda: False)
        monkeypatch.setitem(sys.modules, "OpenEXR", None)  # import OpenEXR raises ImportError
        (tmp_path / "a.exr").write_bytes(b"\x76\x2f\x31\x01" + b"\0" * 64)
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "a.exr")
        one_line(e, "OpenEXR", "pip install openexr")

    @pytest.mark.parametrize("layout", ["RGB", "RGBA", "R,G,B half"])
    def test_exr_read(self, tmp_path, layout):
        """Float EXR files read back exactly, through OpenCV where its build has OpenEXR, else OpenEXR."""
        import OpenEXR

        img = rand_image()
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        if layout == "RGB":
            channels = {"RGB": img}
        elif layout == "RGBA":
            channels = {"RGBA": np.concatenate([img, np.ones_like(img[..., :1])], axis=-1)}
        else:
            img = img.astype(np.float16).astype(np.float32)
            channels = {c: img[..., k].astype(np.float16) for k, c in enumerate("RGB")}
        OpenEXR.File(header, channels).write(str(tmp_path / "a.exr"))
        back, sat = read_image(tmp_path / "a.exr")
        np.testing.assert_array_equal(back, img)
        assert not sat.any()

    def test_exr_garbage_is_clear(self, tmp_path):
        (tmp_path / "a.exr").write_bytes(b"\x76\x2f\x31\x01" + b"\0" * 64)
        with pytest.raises(CaptureError) as e:
            read_image(tmp_path / "a.exr")
        one_line(e, "a.exr", "expected a readable EXR")

    def test_write_bad_shape(self, tmp_path):
        with pytest.raises(InputError) as e:
            write_image(tmp_path / "a.png", np.zeros((4, 4), np.float32))
        one_line(e, "(H, W, 3)", "(4, 4)")

    def test_write_bad_bits(self, tmp_path):
        with pytest.raises(InputError) as e:
            write_image(tmp_path / "a.png", rand_image(), bits=12)
        one_line(e, "8 or 16", "12")

    def test_write_bad_suffix(self, tmp_path):
        with pytest.raises(InputError) as e:
            write_image(tmp_path / "a.jpg", rand_image())
        one_line(e, ".jpg")
