"""Hypothesis strategies that write capture directories (docs/design.md §2.1) and then break them.

A case is a :class:`Recipe` (plain data, so hypothesis can shrink and print it): a valid base
capture (a tiny synthetic one from :func:`torchmetal.synth.synth_capture`, 1–3 shots, written
as 8-bit PNG, 16-bit PNG or float .npy, at its own size or 0×0 / 1×1 / 2×3 pixels) and up to
three mutations of capture.json (wrong JSON types, NaN / ±inf / huge numbers, missing and extra
keys, empty or duplicated shots, undecodable text) or of its files (images missing, empty,
corrupt, truncated, a directory, grayscale, RGBA, wrong size, wrong dtype or rank, pickled, float
NPY with NaN / inf / negative / huge values, all black, all saturated; normals, mask and
saturation flags with wrong shapes, dtypes or NaN).
"""

from __future__ import annotations

import functools
import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from hypothesis import strategies as st

__all__ = ["Recipe", "recipes", "write_recipe", "base_capture"]

BASE_SIZE = 20


@functools.cache
def base_capture(kind: str):
    """A cached tiny synthetic capture: "plain" (flat, no flakes) or "flakes" (bumpy, glints)."""
    from torchmetal.flakes.model import FlakeModel
    from torchmetal.synth import synth_capture

    if kind == "plain":
        return synth_capture(size=BASE_SIZE, shots=3, seed=1, noise=0.005)
    return synth_capture(size=BASE_SIZE, shots=3, seed=2, noise=0.005, bumpy=True,
                         flakes=FlakeModel(density=0.02, seed=3))


# ----------------------------------------------------------------------------------- values

#: JSON values that are wrong somewhere (or everywhere): types, non-finite and extreme numbers
WEIRD = st.sampled_from([
    None, True, False, 0, 1, -1, 2, 0.5, 1e-300, 1e308, -1e308, 1e39, -1e39, 10 ** 400, -(10 ** 400),
    math.nan, math.inf, -math.inf, "", "x", "images/000.png", "NaN", [], [1, 2], [0, 0, 1, 1], [0, 0, 1, 0],
    [math.nan, 0, 1, 1], [1e308, 1e308, 1e308], [[0, 0, 1, 1]], {}, {"a": 1}, {"width": 1, "height": 1},
])

#: numbers for numeric leaves: extremes of float64 and float32, subnormals, signs, huge integers
NUMBERS = st.one_of(
    st.sampled_from([0, -0.0, 1, -1, 1e-300, 5e-324, 1e-45, 3.4e38, 3.5e38, 1e38, 1e300, 1e308, -1e308,
                     10 ** 400, math.nan, math.inf, -math.inf, 2 ** 63, -(2 ** 63)]),
    st.floats(allow_nan=True, allow_infinity=True),
)

#: where in capture.json a value goes ("k": a shot index, "i": a vector component)
JSON_PATHS = [
    ("format",), ("version",), ("color_space",), ("surface",), ("surface", "width"), ("surface", "height"),
    ("shots",), ("shots", "k"), ("shots", "k", "image"), ("shots", "k", "light"), ("shots", "k", "light", "i"),
    ("shots", "k", "light_intensity"), ("shots", "k", "light_intensity", "i"), ("shots", "k", "camera"),
    ("shots", "k", "camera", "i"), ("normals",), ("mask",), ("saturated",),
]

IMAGE_FAULTS = [
    "missing", "empty", "garbage", "truncated", "directory", "gray_png", "rgba_png", "gray16_png", "bad_suffix",
    "wrong_size", "one_px", "black", "saturated", "nan_npy", "inf_npy", "negative_npy", "huge_npy", "tiny_npy",
    "int_npy", "bool_npy", "f16_npy", "f64_npy", "complex_npy", "rank2_npy", "one_channel_npy", "five_channel_npy",
    "rank4_npy", "pickled_npy", "scalar_npy", "rgba_npy",
]
NORMAL_FAULTS = [
    "valid", "missing", "garbage", "nan", "inf", "zero", "int", "f16", "rank2", "wrong_size", "transposed",
    "downward", "horizontal", "huge", "tiny", "unnormalised", "pickled",
]
MASK_FAULTS = [
    "valid", "empty", "one_px", "wrong_size", "garbage", "missing", "nan_npy", "rank3_npy", "rgba_png", "png16",
    "float_npy", "bool_npy", "directory",
]
SAT_FAULTS = ["all", "none", "wrong_shape", "wrong_dtype", "missing", "garbage"]
RAW_JSON = ["", "null", "[]", "{", "\"torchmetal-capture\"", "NaN", "{\"format\": \"torchmetal-capture\"}"]


@dataclass(frozen=True)
class Recipe:
    base: str                      # "plain" | "flakes"
    shots: int                     # 1..3
    encoding: str                  # "png8" | "png16" | "npy"
    color_space: str               # "srgb" | "linear"
    size: tuple[int, int]          # image (H, W) of every shot
    mutations: tuple[tuple, ...]   # applied in order


@st.composite
def _mutation(draw, shots: int):
    kind = draw(st.sampled_from(["set", "delete", "extra", "shots", "raw", "image", "all_images", "normals",
                                 "mask", "saturated"]))
    k = draw(st.integers(0, shots - 1))
    if kind in ("set", "delete"):
        path = draw(st.sampled_from(JSON_PATHS))
        path = tuple(k if p == "k" else draw(st.integers(0, 3)) if p == "i" else p for p in path)
        numeric = isinstance(path[-1], int) or path[-1] in ("width", "height")
        value = draw(NUMBERS if numeric and draw(st.booleans()) else WEIRD)
        return (kind, path, value) if kind == "set" else (kind, path)
    if kind == "extra":
        return (kind, draw(st.sampled_from([(), ("surface",), ("shots", k)])), draw(WEIRD))
    if kind == "shots":
        return (kind, draw(st.sampled_from(["empty", "duplicate", "drop_first", "many_same"])))
    if kind == "raw":
        return (kind, draw(st.sampled_from(RAW_JSON + ["\udcff"])))
    if kind == "image":
        return (kind, k, draw(st.sampled_from(IMAGE_FAULTS)))
    if kind == "all_images":
        return (kind, draw(st.sampled_from(["black", "saturated", "nan_npy", "huge_npy", "one_px"])))
    if kind == "normals":
        return (kind, draw(st.sampled_from(NORMAL_FAULTS)))
    if kind == "mask":
        return (kind, draw(st.sampled_from(MASK_FAULTS)))
    return (kind, draw(st.sampled_from(SAT_FAULTS)))


@st.composite
def recipes(draw, max_mutations: int = 3):
    shots = draw(st.integers(1, 3))
    size = draw(st.sampled_from([(BASE_SIZE, BASE_SIZE)] * 4 + [(0, 0), (1, 1), (2, 3), (BASE_SIZE, 7)]))
    encoding = draw(st.sampled_from(["png8", "png16", "npy"]))
    muts = draw(st.lists(_mutation(shots), min_size=0, max_size=max_mutations))
    return Recipe(draw(st.sampled_from(["plain", "flakes"])), shots, encoding, draw(st.sampled_from(["srgb", "linear"])),
                  size, tuple(muts))


# ---------------------------------------------------------------------------------- writing


def _png(path: Path, arr: np.ndarray) -> None:
    """Write an integer array (H, W[, C]) RGB(A) as PNG via OpenCV (RGB → BGR)."""
    from torchmetal.io.images import _cv2

    cv2 = _cv2()
    if arr.ndim == 3 and arr.shape[2] >= 3:
        arr = np.concatenate([arr[:, :, 2::-1], arr[:, :, 3:]], axis=2)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr))
    assert ok
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(buf.tobytes())


def _encode(linear: np.ndarray, encoding: str, color_space: str) -> np.ndarray:
    """(H, W, 3) linear float → the stored array of ``encoding``."""
    if encoding == "npy":
        return linear.astype(np.float32)
    v = np.clip(linear, 0, 1)
    if color_space == "srgb":
        v = np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)
    top = 255 if encoding == "png8" else 65535
    return np.rint(v * top).astype(np.uint8 if encoding == "png8" else np.uint16)


def _resize(a: np.ndarray, h: int, w: int) -> np.ndarray:
    """Nearest-neighbour resize of (H, W, ...) to (h, w, ...) (0 allowed)."""
    rows = (np.arange(h) * a.shape[0] // max(h, 1)).astype(int)
    cols = (np.arange(w) * a.shape[1] // max(w, 1)).astype(int)
    return a[rows][:, cols]


def _clear(path: Path) -> None:
    """Remove what an earlier mutation left at ``path`` (a file or a directory)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def _write_image(path: Path, stored: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    _clear(path)
    if path.suffix == ".npy":
        np.save(path, stored)
    else:  # PNG bytes (also under a wrong suffix); floats quantised
        if stored.dtype.kind == "f":
            stored = np.rint(np.clip(np.nan_to_num(stored), 0, 1) * 65535).astype(np.uint16)
        if min(stored.shape[:2]) == 0:
            path.write_bytes(b"")
            return
        _png(path, stored)


class _Writer:
    """Writes a recipe's base capture, then applies its mutations to files and to the JSON."""

    def __init__(self, root: Path, r: Recipe):
        self.root, self.r = root, r
        syn = base_capture(r.base)
        cap = syn.capture
        self.h, self.w = r.size
        self.encoding = "npy" if 0 in r.size else r.encoding
        self.full = [cap.images[k].permute(1, 2, 0).numpy() for k in range(r.shots)]
        self.linear = [_resize(a, self.h, self.w) for a in self.full]
        self.normals = _resize(cap.normals.permute(1, 2, 0).numpy(), self.h, self.w).astype(np.float32)
        suffix = ".npy" if self.encoding == "npy" else ".png"
        self.meta = {
            "format": "torchmetal-capture", "version": 1,
            "color_space": "linear" if self.encoding == "npy" else r.color_space,
            "surface": {"width": float(cap.size[0]), "height": float(cap.size[1])},
            "shots": [{"image": f"images/{k:03d}{suffix}", "light": cap.lights[k].tolist(),
                       "light_intensity": cap.intensities[k].tolist(), "camera": cap.cameras[k].tolist()}
                      for k in range(r.shots)],
        }
        for k in range(r.shots):
            self.put_image(k, self.linear[k])
        self.raw_text: str | None = None

    # -- images ----------------------------------------------------------------------------

    def image_path(self, k: int) -> Path:
        return self.root / self.meta["shots"][k]["image"]

    def put_image(self, k: int, linear: np.ndarray) -> None:
        """Write shot k from linear values in the capture's encoding."""
        _write_image(self.image_path(k), _encode(linear, self.encoding, self.meta.get("color_space")))

    def break_image(self, k: int, fault: str) -> None:
        shots = self.meta.get("shots")
        if not isinstance(shots, list) or k >= len(shots) or not isinstance(shots[k], dict):
            return
        if not isinstance(shots[k].get("image"), str) or not shots[k]["image"]:
            return
        f = self.image_path(k)
        if not f.parent.is_dir() or f.is_dir():
            return
        lin = self.linear[min(k, len(self.linear) - 1)]
        if fault == "missing":
            f.unlink(missing_ok=True)
        elif fault == "empty":
            f.write_bytes(b"")
        elif fault == "garbage":
            f.write_bytes(bytes(range(256)) * 3)
        elif fault == "truncated":
            data = f.read_bytes() if f.is_file() else b"\x89PNG"
            f.write_bytes(data[: max(1, len(data) // 2)])
        elif fault == "directory":
            f.unlink(missing_ok=True)
            f.mkdir()
        elif fault in ("gray_png", "rgba_png", "gray16_png") and min(self.h, self.w) > 0:
            g = (np.clip(lin.mean(axis=2), 0, 1) * (65535 if fault == "gray16_png" else 255))
            g = g.astype(np.uint16 if fault == "gray16_png" else np.uint8)
            if fault == "rgba_png":
                g = np.dstack([g, g, g, np.full_like(g, 128)])
            self.meta["shots"][k]["image"] = f"images/{k:03d}_{fault}.png"
            _png(self.image_path(k), g)
        elif fault == "bad_suffix":
            new = f.with_suffix(".jpg")
            f.rename(new)
            self.meta["shots"][k]["image"] = str(new.relative_to(self.root))
        elif fault in ("wrong_size", "one_px"):
            h, w = (1, 1) if fault == "one_px" else (self.h + 1, self.w + 1)
            enc = "npy" if f.suffix == ".npy" else self.encoding
            full = self.full[min(k, len(self.full) - 1)]
            _write_image(f, _encode(_resize(full, h, w), enc, self.meta.get("color_space")))
        elif fault == "black":
            self.put_image(k, np.zeros_like(lin))
        elif fault == "saturated":
            self.put_image(k, np.ones_like(lin) * (1.0 if self.encoding != "npy" else 4.0))
        else:  # float .npy faults: replace the file by an array
            self.meta["shots"][k]["image"] = f"images/{k:03d}_{fault}.npy"
            p = self.image_path(k)
            p.parent.mkdir(parents=True, exist_ok=True)
            a = lin.astype(np.float32).copy()
            if fault == "nan_npy":
                a[a.shape[0] // 2:, :, 1] = np.nan
            elif fault == "inf_npy":
                a[:1, :1] = np.inf
            elif fault == "negative_npy":
                a[:, : max(1, a.shape[1] // 3)] = -0.5
            elif fault == "huge_npy":
                a = a * np.float32(1e37)
            elif fault == "tiny_npy":
                a = a * np.float32(1e-40)  # subnormal
            elif fault == "int_npy":
                a = (a * 1000).astype(np.int32)
            elif fault == "bool_npy":
                a = a > 0.1
            elif fault == "f16_npy":
                a = a.astype(np.float16)
            elif fault == "f64_npy":
                a = a.astype(np.float64)
            elif fault == "complex_npy":
                a = a.astype(np.complex64)
            elif fault == "rank2_npy":
                a = a[:, :, 0]
            elif fault == "one_channel_npy":
                a = a[:, :, :1]
            elif fault == "five_channel_npy":
                a = np.concatenate([a, a[:, :, :2]], axis=2)
            elif fault == "rgba_npy":
                a = np.concatenate([a, np.ones_like(a[:, :, :1])], axis=2)
            elif fault == "rank4_npy":
                a = a[None]
            elif fault == "scalar_npy":
                a = np.float32(0.5)
            elif fault == "pickled_npy":
                np.save(p, np.array([{"not": "an image"}], dtype=object), allow_pickle=True)
                return
            np.save(p, a)

    # -- side files ------------------------------------------------------------------------

    def normals_file(self, fault: str) -> None:
        self.meta["normals"] = "normals.npy"
        f = self.root / "normals.npy"
        _clear(f)
        n = self.normals.copy()
        base = base_capture("flakes").capture.normals.permute(1, 2, 0).numpy()
        bumpy = _resize(base, self.h, self.w).astype(np.float32)
        arrays = {
            "valid": bumpy, "nan": np.where(np.arange(n.size).reshape(n.shape) % 7 == 0, np.nan, n),
            "inf": np.where(np.arange(n.size).reshape(n.shape) % 5 == 0, np.inf, n), "zero": np.zeros_like(n),
            "int": np.rint(n).astype(np.int32), "f16": bumpy.astype(np.float16), "rank2": n[..., 2],
            "wrong_size": _resize(base, self.h + 2, self.w + 1), "transposed": n.transpose(2, 0, 1),
            "downward": -bumpy, "horizontal": np.broadcast_to(np.float32([1, 0, 0]), n.shape).copy(),
            "huge": bumpy.astype(np.float64) * 1e200, "tiny": bumpy.astype(np.float64) * 1e-200,
            "unnormalised": bumpy * 3.0,
        }
        if fault == "missing":
            return
        if fault == "garbage":
            f.write_bytes(b"\x93NUMPY garbage")
        elif fault == "pickled":
            np.save(f, np.array([None], dtype=object), allow_pickle=True)
        else:
            np.save(f, arrays[fault])

    def mask_file(self, fault: str) -> None:
        h, w = self.h, self.w
        name = "mask.npy" if fault.endswith("_npy") else "mask.png"
        self.meta["mask"] = name
        f = self.root / name
        _clear(f)
        m = np.zeros((h, w), np.uint8)
        m[: h // 2 + 1] = 255
        if fault == "missing":
            return
        if fault == "directory":
            f.mkdir()
        elif fault == "garbage":
            f.write_bytes(b"not a png")
        elif min(h, w) == 0 and name == "mask.png":
            f.write_bytes(b"")  # a 0x0 PNG cannot be encoded: an empty file instead
        elif fault == "valid":
            _png(f, m)
        elif fault == "empty":
            _png(f, np.zeros_like(m))
        elif fault == "one_px":
            m[:] = 0
            m[0, 0] = 255
            _png(f, m)
        elif fault == "wrong_size":
            _png(f, np.full((h + 1, w + 3), 255, np.uint8))
        elif fault == "rgba_png":
            _png(f, np.dstack([m, m, m, m]))
        elif fault == "png16":
            _png(f, m.astype(np.uint16) * 257)
        elif fault == "nan_npy":
            np.save(f, np.where(m > 0, np.nan, 0.0))
        elif fault == "rank3_npy":
            np.save(f, (m > 0)[None])
        elif fault == "float_npy":
            np.save(f, m.astype(np.float32) / 255)
        elif fault == "bool_npy":
            np.save(f, m > 0)

    def saturated_file(self, fault: str) -> None:
        self.meta["saturated"] = "saturated.npy"
        f = self.root / "saturated.npy"
        _clear(f)
        shape = (len(self.meta["shots"]) if isinstance(self.meta["shots"], list) else 1, self.h, self.w, 3)
        if fault == "missing":
            return
        if fault == "garbage":
            f.write_bytes(b"\x00" * 10)
        elif fault == "all":
            np.save(f, np.ones(shape, bool))
        elif fault == "none":
            np.save(f, np.zeros(shape, bool))
        elif fault == "wrong_shape":
            np.save(f, np.zeros(shape[1:], bool))
        elif fault == "wrong_dtype":
            np.save(f, np.zeros(shape, np.uint8))

    # -- capture.json ----------------------------------------------------------------------

    def _walk(self, path: tuple) -> tuple[object, object] | None:
        """(container, key) of ``path`` in the JSON, or None when the path no longer exists."""
        node: object = self.meta
        for p in path[:-1]:
            if isinstance(node, dict) and p in node:
                node = node[p]
            elif isinstance(node, list) and isinstance(p, int) and p < len(node):
                node = node[p]
            else:
                return None
        key = path[-1]
        if isinstance(node, dict) and isinstance(key, str):
            return node, key
        if isinstance(node, list) and isinstance(key, int) and key < len(node):
            return node, key
        return None

    def apply(self, m: tuple) -> None:
        kind = m[0]
        if kind == "set":
            at = self._walk(m[1])
            if at is not None:
                at[0][at[1]] = m[2]
        elif kind == "delete":
            at = self._walk(m[1])
            if at is not None and (isinstance(at[0], list) or at[1] in at[0]):
                del at[0][at[1]]
        elif kind == "extra":
            node = self._walk(m[1] + ("_",)) if m[1] else (self.meta, "_")
            if node is not None and isinstance(node[0], dict):
                node[0]["unexpected_key"] = m[2]
        elif kind == "shots":
            shots = self.meta.get("shots")
            if isinstance(shots, list):
                if m[1] == "empty":
                    shots.clear()
                elif m[1] == "duplicate" and shots:
                    shots.append(json.loads(json.dumps(shots[0])))
                elif m[1] == "drop_first" and shots:
                    shots.pop(0)
                elif m[1] == "many_same" and shots:
                    shots.extend(json.loads(json.dumps(shots[0])) for _ in range(4))
        elif kind == "raw":
            self.raw_text = m[1]
        elif kind == "image":
            self.break_image(m[1], m[2])
        elif kind == "all_images":
            for k in range(len(self.meta["shots"]) if isinstance(self.meta.get("shots"), list) else 0):
                self.break_image(k, m[1])
        elif kind == "normals":
            self.normals_file(m[1])
        elif kind == "mask":
            self.mask_file(m[1])
        elif kind == "saturated":
            self.saturated_file(m[1])

    def finish(self) -> Path:
        f = self.root / "capture.json"
        if self.raw_text is not None:
            f.write_bytes(self.raw_text.encode("utf-8", "surrogateescape"))
        else:
            f.write_text(json.dumps(self.meta, indent=1))  # NaN/Infinity literals and 10**400 as written
        return self.root


def write_recipe(root: Path, r: Recipe) -> Path:
    """Write the capture of ``r`` into the new directory ``root``; returns it."""
    root.mkdir(parents=True)
    w = _Writer(root, r)
    for m in r.mutations:
        w.apply(m)
    return w.finish()
