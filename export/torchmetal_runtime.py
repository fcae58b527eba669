#!/usr/bin/env python3
"""torchmetal runtime: relight an exported torchmetal renderer with numpy + onnxruntime only.

No torch, no torchmetal: copy this one file next to a ``renderer.onnx`` and use it.

```python
from torchmetal_runtime import Renderer
r = Renderer("renderer.onnx")
img = r.render([0.3, 0.2, 1.0, 0.0], [1, 1, 1], [0, 0, 1, 0])   # (1, 3, H, W) float32 linear
frames = r.orbit(36, elevation=40)                                # (36, 3, H, W)
write_apng("orbit.png", [to_srgb8(f) for f in frames], fps=24)
```
Command line::

    python torchmetal_runtime.py renderer.onnx --light 0.3 0.2 1 0 --camera 0 0 1 0 -o frame.png
    python torchmetal_runtime.py renderer.onnx --orbit 36 -o orbit.png      # animated PNG (APNG)
    python torchmetal_runtime.py renderer.onnx --orbit 36 -o orbit.gif      # GIF (needs Pillow)
    python torchmetal_runtime.py renderer.onnx --time

Conventions (torchmetal docs/design.md §2.1/2.4): the sample is the plane z = 0 centred at the origin;
``light`` and ``camera`` are homogeneous (x, y, z, w): w = 1 a position, w = 0 a direction
towards the light / camera; ``light_intensity`` is RGB radiant intensity (point light) or
irradiance (directional light). Images are linear radiance (B, 3, H, W).
Bad input raises :class:`RuntimeInputError` (a ``ValueError``) with a one-line message; the CLI
prints it and exits with status 2.
"""

from __future__ import annotations

import argparse
import math
import os
import struct
import sys
import time
import zlib

import numpy as np

__all__ = [
    "Renderer", "RuntimeInputError", "orbit_lights", "to_srgb8", "write_png", "write_apng",
    "write_gif", "write_animation", "main",
]

INPUTS = (("light", 4), ("light_intensity", 3), ("camera", 4))


class RuntimeInputError(ValueError):
    """Bad renderer file or bad light/camera input (one-line message)."""


def _as_batch(x, name: str, width: int) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise RuntimeInputError(f"{name}: expected numbers of shape ({width},) or (B, {width}), found {type(x).__name__}") from None
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != width or a.shape[0] < 1:
        raise RuntimeInputError(f"{name}: expected shape ({width},) or (B, {width}), found {tuple(np.shape(x))}")
    if not np.isfinite(a).all():
        bad = int((~np.isfinite(a)).sum())
        raise RuntimeInputError(f"{name}: expected finite values, found {bad} non-finite of {a.size}")
    if np.abs(a).max() > np.finfo(np.float32).max:
        raise RuntimeInputError(f"{name}: expected values within float32 range, found {np.abs(a).max():.3g}")
    return a.astype(np.float32)


class Renderer:
    """An exported torchmetal renderer in onnxruntime (CPU).

    Args:
        path: the ``renderer.onnx`` file.
        threads: intra-op threads (None: onnxruntime's default, one per core).

    Attributes: ``height``, ``width``, ``metadata`` (dict of the file's metadata), ``session``.
    """

    def __init__(self, path: str | os.PathLike, *, threads: int | None = None) -> None:
        try:
            import onnxruntime as ort
        except ImportError:
            raise RuntimeInputError("onnxruntime: expected it installed (pip install onnxruntime), found it missing") from None
        path = os.fspath(path)
        if not os.path.isfile(path):
            raise RuntimeInputError(f"{path}: expected an ONNX renderer file, found nothing")
        so = ort.SessionOptions()
        so.log_severity_level = 3
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        # no spin-waiting between ops: threads that spin steal shared cores (2-3x slower frames under load)
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        if threads is not None:
            if int(threads) < 0:
                raise RuntimeInputError(f"threads: expected >= 0, found {threads}")
            so.intra_op_num_threads = int(threads)
        try:
            self.session = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises several types
            first = (str(e).strip().splitlines() or [type(e).__name__])[0]
            raise RuntimeInputError(f"{path}: expected a loadable ONNX renderer, found {first[:200]}") from None
        self.path = path
        self.threads = threads
        got = {i.name: i for i in self.session.get_inputs()}
        for name, width in INPUTS:
            i = got.get(name)
            if i is None or len(i.shape) != 2 or i.shape[1] != width or i.type != "tensor(float)":
                found = "missing" if i is None else f"{i.type} {i.shape}"
                raise RuntimeInputError(f"{path}: expected input {name} float32 (B, {width}), found {found}")
        outs = self.session.get_outputs()
        if len(outs) != 1 or len(outs[0].shape) != 4:
            raise RuntimeInputError(f"{path}: expected one output image (B, 3, H, W), found {[(o.name, o.shape) for o in outs]}")
        self.output_name = outs[0].name
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)
        shape = outs[0].shape
        h = shape[2] if isinstance(shape[2], int) else int(self.metadata.get("height", 0)) or None
        w = shape[3] if isinstance(shape[3], int) else int(self.metadata.get("width", 0)) or None
        self.height, self.width = h, w
        self.surface = (float(self.metadata.get("surface_width", 1.0)), float(self.metadata.get("surface_height", 1.0)))

    def __repr__(self) -> str:
        return f"Renderer({self.path!r}, {self.height}x{self.width})"

    def render(self, light, light_intensity=(1.0, 1.0, 1.0), camera=(0.0, 0.0, 1.0, 0.0)) -> np.ndarray:
        """Render B shots.

        Args:
            light: (4,) or (B, 4); light_intensity: (3,) or (B, 3); camera: (4,) or (B, 4).
                A single row is broadcast to the batch of the others.

        Returns:
            (B, 3, H, W) float32 linear radiance.
        """
        arrays = [_as_batch(x, name, width) for x, (name, width) in zip((light, light_intensity, camera), INPUTS)]
        b = max(a.shape[0] for a in arrays)
        for k, (a, (_name, _)) in enumerate(zip(arrays, INPUTS)):
            if a.shape[0] not in (1, b):
                sizes = ", ".join(f"{n} {x.shape[0]}" for x, (n, _) in zip(arrays, INPUTS))
                raise RuntimeInputError(f"batch: expected equal batch sizes (or 1), found {sizes}")
            if a.shape[0] != b:
                arrays[k] = np.repeat(a, b, axis=0)
        feeds = {name: a for a, (name, _) in zip(arrays, INPUTS)}
        return self.session.run([self.output_name], feeds)[0]

    __call__ = render

    def orbit(
        self,
        frames: int,
        *,
        elevation: float = 45.0,
        distance: float | None = None,
        light_intensity=(1.0, 1.0, 1.0),
        camera=(0.0, 0.0, 1.0, 0.0),
        batch: int = 8,
    ) -> np.ndarray:
        """A light circling the sample: ``frames`` renders (frames, 3, H, W).

        ``distance`` None gives a directional light; otherwise a point light at that distance
        (its intensity is scaled by distance² so the irradiance at the centre stays the same).
        """
        lights = orbit_lights(frames, elevation=elevation, distance=distance)
        intensity = _as_batch(light_intensity, "light_intensity", 3)
        if distance is not None:
            intensity = intensity * np.float32(distance) ** 2
        out = []
        for i in range(0, frames, max(1, int(batch))):
            chunk = lights[i:i + batch]
            out.append(self.render(chunk, np.repeat(intensity, len(chunk), 0), camera))
        return np.concatenate(out)

    def time(self, *, repeats: int = 20, batch: int = 1, warmup: int = 3) -> dict:
        """Frame time for ``batch`` shots per call (a near point light, point camera).

        Returns:
            dict: height, width, batch, repeats, threads, ms_median, ms_min, ms_mean,
            ms_per_shot, fps, onnxruntime version.
        """
        import onnxruntime as ort

        if repeats < 1 or batch < 1:
            raise RuntimeInputError(f"time: expected repeats >= 1 and batch >= 1, found {repeats}, {batch}")
        w, h = self.surface
        ext = max(w, h)
        light = np.tile(np.array([[0.1 * ext, 0.05 * ext, 0.6 * ext, 1.0]], np.float32), (batch, 1))
        cam = np.tile(np.array([[-0.1 * ext, -0.05 * ext, 0.8 * ext, 1.0]], np.float32), (batch, 1))
        inten = np.tile(np.array([[0.37 * ext * ext] * 3], np.float32), (batch, 1))
        for _ in range(max(0, warmup)):
            self.render(light, inten, cam)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            self.render(light, inten, cam)
            times.append(time.perf_counter() - t0)
        ms = np.array(times) * 1e3
        med = float(np.median(ms))
        return {
            "height": self.height, "width": self.width, "batch": batch, "repeats": repeats,
            "threads": self.threads or self.session.get_session_options().intra_op_num_threads or os.cpu_count(),
            "ms_median": med, "ms_min": float(ms.min()), "ms_mean": float(ms.mean()),
            "ms_per_shot": med / batch, "fps": 1e3 * batch / med, "onnxruntime": ort.__version__,
        }


def orbit_lights(frames: int, *, elevation: float = 45.0, distance: float | None = None) -> np.ndarray:
    """(frames, 4) lights on a circle at ``elevation`` degrees, azimuth 0..360° (exclusive).

    ``distance`` None: directional (w = 0); else point lights at that distance (w = 1).
    """
    if int(frames) < 1:
        raise RuntimeInputError(f"frames: expected >= 1, found {frames}")
    if not (math.isfinite(elevation) and -90.0 <= elevation <= 90.0):
        raise RuntimeInputError(f"elevation: expected degrees in [-90, 90], found {elevation}")
    if distance is not None and not (math.isfinite(distance) and distance > 0):
        raise RuntimeInputError(f"distance: expected a positive number, found {distance}")
    az = np.arange(int(frames)) * (2 * np.pi / int(frames))
    el = math.radians(elevation)
    d = np.stack([np.cos(az) * math.cos(el), np.sin(az) * math.cos(el), np.full_like(az, math.sin(el))], 1)
    r = 1.0 if distance is None else float(distance)
    w = 0.0 if distance is None else 1.0
    return np.concatenate([d * r, np.full((len(az), 1), w)], 1).astype(np.float32)


def to_srgb8(image: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """(3, H, W) linear radiance → (H, W, 3) uint8 sRGB (scaled by ``exposure``, clipped)."""
    x = np.asarray(image, dtype=np.float32)
    if x.ndim != 3 or x.shape[0] != 3:
        raise RuntimeInputError(f"image: expected shape (3, H, W), found {x.shape}")
    x = np.clip(np.nan_to_num(x * np.float32(exposure), nan=0.0), 0.0, 1.0).transpose(1, 2, 0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.clip(np.round(srgb * 255.0), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------ image writers
def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _check_rgb8(rgb: np.ndarray) -> np.ndarray:
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
        raise RuntimeInputError(f"frame: expected (H, W, 3) uint8, found {a.dtype} {a.shape}")
    return np.ascontiguousarray(a)


def _idat(rgb: np.ndarray, level: int) -> bytes:
    # filter type 1 ("Sub") on every row: small, fast and lossless
    h, w, _ = rgb.shape
    rows = rgb.reshape(h, w * 3).astype(np.int16)
    sub = rows.copy()
    sub[:, 3:] -= rows[:, :-3]
    raw = np.empty((h, w * 3 + 1), np.uint8)
    raw[:, 0] = 1
    raw[:, 1:] = (sub & 0xFF).astype(np.uint8)
    return zlib.compress(raw.tobytes(), level)


def _ihdr(h: int, w: int) -> bytes:
    return _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))


def _atomic_write(path: str, data: bytes) -> None:
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def write_png(path: str | os.PathLike, rgb: np.ndarray, *, level: int = 6) -> str:
    """Write an (H, W, 3) uint8 image as PNG (pure numpy + zlib)."""
    rgb = _check_rgb8(rgb)
    h, w, _ = rgb.shape
    data = b"\x89PNG\r\n\x1a\n" + _ihdr(h, w) + _chunk(b"IDAT", _idat(rgb, level)) + _chunk(b"IEND", b"")
    _atomic_write(os.fspath(path), data)
    return os.fspath(path)


def write_apng(path: str | os.PathLike, frames, *, fps: float = 24.0, loops: int = 0, level: int = 6) -> str:
    """Write (H, W, 3) uint8 frames as an animated PNG (APNG; plain viewers show frame 0)."""
    frames = [_check_rgb8(f) for f in frames]
    if not frames:
        raise RuntimeInputError("frames: expected at least one frame, found none")
    h, w, _ = frames[0].shape
    if any(f.shape != frames[0].shape for f in frames):
        raise RuntimeInputError(f"frames: expected equal shapes, found {sorted({f.shape for f in frames})}")
    if not (math.isfinite(fps) and fps > 0):
        raise RuntimeInputError(f"fps: expected a positive number, found {fps}")
    delay_den = 1000
    delay_num = max(1, int(round(delay_den / fps)))
    parts = [b"\x89PNG\r\n\x1a\n", _ihdr(h, w), _chunk(b"acTL", struct.pack(">II", len(frames), loops))]
    seq = 0
    for k, f in enumerate(frames):
        parts.append(_chunk(b"fcTL", struct.pack(">IIIIIHHBB", seq, w, h, 0, 0, delay_num, delay_den, 0, 0)))
        seq += 1
        data = _idat(f, level)
        if k == 0:
            parts.append(_chunk(b"IDAT", data))
        else:
            parts.append(_chunk(b"fdAT", struct.pack(">I", seq) + data))
            seq += 1
    parts.append(_chunk(b"IEND", b""))
    _atomic_write(os.fspath(path), b"".join(parts))
    return os.fspath(path)


def write_gif(path: str | os.PathLike, frames, *, fps: float = 24.0, loops: int = 0) -> str:
    """Write frames as an animated GIF; needs Pillow (else :class:`RuntimeInputError`)."""
    try:
        from PIL import Image
    except ImportError:
        raise RuntimeInputError("gif: expected Pillow installed for GIF output, found it missing (write .png for APNG instead)") from None
    frames = [_check_rgb8(f) for f in frames]
    if not frames:
        raise RuntimeInputError("frames: expected at least one frame, found none")
    imgs = [Image.fromarray(f) for f in frames]
    tmp = f"{os.fspath(path)}.tmp{os.getpid()}"
    imgs[0].save(tmp, format="GIF", save_all=True, append_images=imgs[1:], duration=int(round(1000 / fps)), loop=loops)
    os.replace(tmp, os.fspath(path))
    return os.fspath(path)


def write_animation(path: str | os.PathLike, frames, *, fps: float = 24.0) -> str:
    """APNG for ``.png``/``.apng``, GIF for ``.gif`` (Pillow), by the file extension."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext in (".png", ".apng"):
        return write_apng(path, frames, fps=fps)
    if ext == ".gif":
        return write_gif(path, frames, fps=fps)
    raise RuntimeInputError(f"{path}: expected an animation file ending in .png, .apng or .gif, found {ext or 'no extension'}")


# ------------------------------------------------------------------------------------ command line
def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="torchmetal_runtime.py",
        description="Relight an exported torchmetal renderer (numpy + onnxruntime only).",
    )
    p.add_argument("renderer", help="renderer.onnx exported by torchmetal")
    p.add_argument("--light", type=float, nargs=4, metavar=("X", "Y", "Z", "W"), default=[0.3, 0.2, 1.0, 0.0],
                   help="homogeneous light: w=1 position, w=0 direction (default: %(default)s)")
    p.add_argument("--camera", type=float, nargs=4, metavar=("X", "Y", "Z", "W"), default=[0.0, 0.0, 1.0, 0.0],
                   help="homogeneous camera (default: orthographic from above, %(default)s)")
    p.add_argument("--intensity", type=float, nargs=3, metavar=("R", "G", "B"), default=[1.0, 1.0, 1.0],
                   help="light intensity (point) or irradiance (directional) (default: %(default)s)")
    p.add_argument("-o", "--output", help="output image: .png (8-bit sRGB), .npy (float32 linear); with --orbit .png (APNG) or .gif")
    p.add_argument("--exposure", type=float, default=1.0, help="scale before sRGB encoding (default: %(default)s)")
    p.add_argument("--orbit", type=int, metavar="N", help="render N frames of a light circling the sample")
    p.add_argument("--elevation", type=float, default=45.0, help="orbit elevation in degrees (default: %(default)s)")
    p.add_argument("--distance", type=float, help="orbit with a point light at this distance (default: directional)")
    p.add_argument("--fps", type=float, default=24.0, help="orbit frame rate (default: %(default)s)")
    p.add_argument("--time", action="store_true", help="print the frame time for one light")
    p.add_argument("--repeats", type=int, default=20, help="timed runs for --time (default: %(default)s)")
    p.add_argument("--batch", type=int, default=1, help="shots per run for --time (default: %(default)s)")
    p.add_argument("--threads", type=int, help="onnxruntime intra-op threads (default: one per core)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if not (args.time or args.output):
            raise RuntimeInputError("arguments: expected -o OUTPUT or --time, found neither")
        if not (math.isfinite(args.exposure) and args.exposure > 0):
            raise RuntimeInputError(f"--exposure: expected a positive number, found {args.exposure}")
        r = Renderer(args.renderer, threads=args.threads)
        if args.time:
            t = r.time(repeats=args.repeats, batch=args.batch)
            print(
                f"{os.path.basename(args.renderer)} {t['height']}x{t['width']}: {t['ms_median']:.2f} ms median "
                f"({t['ms_min']:.2f} min) per call of {t['batch']} shot(s) over {t['repeats']} runs, "
                f"{t['fps']:.1f} shots/s, {t['threads']} threads, onnxruntime {t['onnxruntime']}"
            )
        if args.output:
            out = args.output
            ext = os.path.splitext(out)[1].lower()
            if args.orbit is not None:
                frames = r.orbit(args.orbit, elevation=args.elevation, distance=args.distance,
                                 light_intensity=args.intensity, camera=args.camera)
                if ext == ".npy":
                    np.save(out, frames)
                else:
                    write_animation(out, [to_srgb8(f, args.exposure) for f in frames], fps=args.fps)
                print(f"wrote {len(frames)} frames {r.height}x{r.width} -> {out}")
            else:
                img = r.render(args.light, args.intensity, args.camera)[0]
                if ext == ".npy":
                    np.save(out, img)
                elif ext == ".png":
                    write_png(out, to_srgb8(img, args.exposure))
                else:
                    raise RuntimeInputError(f"{out}: expected an output ending in .png or .npy, found {ext or 'no extension'}")
                print(f"wrote {r.height}x{r.width} -> {out}")
    except RuntimeInputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"error: {e.filename or ''}: {e.strerror or e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
