"""Capture directories (docs/design.md §2.1) ↔ :class:`Capture` tensors.

```
capture/
  capture.json      format "torchmetal-capture", version 1
  images/…          one RGB image per shot: 8/16-bit PNG, float .npy or .exr
  normals.npy       optional (H, W, 3) unit normals; default (0, 0, 1)
  mask.png          optional; nonzero = sample
  saturated.npy     optional torchmetal extension (key "saturated"): (N, H, W, 3) bool clipping
                    flags that the image encoding cannot carry itself (e.g. float .npy images);
                    other readers may ignore it
```
Loading decodes everything once (BGR, uint8/16, sRGB) into linear float32 tensors and checks
every value a renderer relies on; each problem is a one-line :class:`CaptureError` naming the
file, what was expected and what was found. Saving: :mod:`torchmetal.io.capture_save`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchmetal.errors import CaptureError
from torchmetal.geometry import is_flat
from torchmetal.io.capture_checks import (
    REFLECTANCE_MAX,
    check_camera,
    check_exposure,
    check_intensity,
    check_light,
    check_light_camera,
    check_pixels,
    check_size,
    numbers,
    shape_error,
    short_repr,
)
from torchmetal.io.images import _cv2, code_table, decode_planes, read_raw, srgb_to_linear
from torchmetal.memory import is_large, release_free_memory

__all__ = ["Capture", "load_capture", "check_light_camera", "read_meta", "parse_meta", "load_mask", "check_pixels",
           "FORMAT", "VERSION", "COLOR_SPACES", "UNIT_TOL", "REFLECTANCE_MAX"]

FORMAT = "torchmetal-capture"
VERSION = 1
COLOR_SPACES = ("srgb", "linear")
_SHOT_KEYS = ("image", "light", "light_intensity", "camera")
_TOP_KEYS = ("color_space", "surface", "shots")
UNIT_TOL = 1e-6  # normals within this of unit length are kept bit-exact


# ---------------------------------------------------------------------------------- Capture


@dataclass(kw_only=True, repr=False, eq=False)
class Capture:
    """N photos of a sample under known lights and cameras, decoded to linear RGB.

    Attributes:
        images: (N, 3, H, W) float linear RGB.
        normals: (3, H, W) unit normals, world frame; default (0, 0, 1) (an expanded view: read-only).
        mask: (1, H, W) bool, True on the sample; default all True.
        lights: (N, 4) homogeneous (w = 1 position, w = 0 direction to the light).
        intensities: (N, 3) radiant intensity (point) or irradiance (directional), linear.
        cameras: (N, 4) homogeneous (w = 1 position, w = 0 orthographic direction).
        size: (width, height) of the surface in scene units.
        saturated: (N, 3, H, W) bool, True where the recorded value was clipped.
        names: N image paths as in capture.json (relative to the capture directory).
        color_space: encoding of the source files ("srgb" or "linear"); ``images`` are always
            linear.
        normals_given: True when the capture came with its own normal map (normals.npy, or ``normals``
            passed in), flat or not: the fit keeps it (docs/design.md §2.5); False for the default (0, 0, 1).

    Built in Python, the missing optional fields get their defaults and everything is checked
    (:meth:`validate`); a bad field raises :class:`CaptureError`.
    """

    images: Tensor
    normals: Tensor | None = None
    mask: Tensor | None = None
    lights: Tensor
    intensities: Tensor
    cameras: Tensor
    size: tuple[float, float]
    saturated: Tensor | None = None
    names: list[str] = field(default_factory=list)
    color_space: str = "linear"
    normals_given: bool | None = None  # None: whether ``normals`` was passed

    def __post_init__(self) -> None:
        x = self.images
        if not isinstance(x, Tensor) or x.dim() != 4 or x.shape[1] != 3:
            raise shape_error("images", "(N, 3, H, W)", x)
        n, _, h, w = x.shape
        # a replace() that keeps normals carries the flag over; normals=None always means none given
        self.normals_given = self.normals is not None and self.normals_given is not False
        if self.normals is None:  # flat: one (3,) normal seen as (3, H, W) — no per-pixel storage
            self.normals = torch.tensor([0.0, 0.0, 1.0], dtype=x.dtype, device=x.device).view(3, 1, 1).expand(3, h, w)
        if self.mask is None:
            self.mask = torch.ones(1, h, w, dtype=torch.bool, device=x.device)
        if self.saturated is None:
            self.saturated = torch.zeros(x.shape, dtype=torch.bool, device=x.device)
        if not self.names:
            self.names = [f"images/{k:03d}.png" for k in range(n)]
        self.names = list(self.names)
        self.size = check_size(self.size, "Capture.size")
        self.validate()

    # -- shape and value checks -------------------------------------------------------------

    def validate(self) -> "Capture":
        """Check shapes, dtypes and values; raises :class:`CaptureError`. Returns ``self``."""
        x = self.images
        if not isinstance(x, Tensor) or x.dim() != 4 or x.shape[1] != 3 or x.shape[0] < 1:
            raise shape_error("images", "(N >= 1, 3, H, W)", x)
        if not x.is_floating_point():
            raise CaptureError(f"Capture.images: expected a floating-point tensor, found dtype {x.dtype}")
        n, _, h, w = x.shape
        if h < 1 or w < 1:
            raise CaptureError(f"Capture.images: expected at least 1x1 pixels, found {w}x{h} (width x height)")
        shapes = {
            "normals": ((3, h, w), None), "mask": ((1, h, w), torch.bool),
            "lights": ((n, 4), None), "intensities": ((n, 3), None), "cameras": ((n, 4), None),
            "saturated": ((n, 3, h, w), torch.bool),
        }
        for name, (shape, dtype) in shapes.items():
            t = getattr(self, name)
            if not isinstance(t, Tensor) or tuple(t.shape) != shape:
                raise shape_error(name, str(shape), t)
            if dtype is None and not t.is_floating_point():
                raise CaptureError(f"Capture.{name}: expected a floating-point tensor, found dtype {t.dtype}")
            if dtype is not None and t.dtype != dtype:
                raise CaptureError(f"Capture.{name}: expected dtype {dtype}, found {t.dtype}")
            if t.device != x.device:
                raise CaptureError(f"Capture.{name}: expected device {x.device} (as images), found {t.device}")
        if not bool(self.mask.view(torch.uint8).amax()):  # uint8 amax: no full-size bool reduction
            raise CaptureError("Capture.mask: expected at least one pixel on the sample (True), found none")
        if len(self.names) != n:
            raise CaptureError(f"Capture.names: expected {n} image names, found {len(self.names)}")
        if self.color_space not in COLOR_SPACES:
            raise CaptureError(f"Capture.color_space: expected one of {list(COLOR_SPACES)}, found {self.color_space!r}")
        peaks = [check_pixels(x[k], f"Capture.images[{k}] ({self.names[k]})") for k in range(n)]  # shot by shot
        nrm = self.normals
        if not bool(torch.isfinite(nrm).all()):
            raise CaptureError("Capture.normals: expected finite unit vectors, found NaN/Inf")
        length = torch.linalg.vector_norm(nrm.double(), dim=0)
        worst = float((length - 1).abs().max())
        if worst > 1e-3:
            raise CaptureError(f"Capture.normals: expected unit vectors, found a length off by {worst:.3g}")
        labels = [f"Capture shot {k} ({self.names[k]})" for k in range(n)]
        check_light_camera(self.lights, self.intensities, self.cameras, error=CaptureError, labels=labels)
        check_exposure(peaks, self.lights, self.intensities, self.size, labels)
        return self

    # -- views ------------------------------------------------------------------------------

    @property
    def num_shots(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[2])

    @property
    def width(self) -> int:
        return int(self.images.shape[3])

    @property
    def flat(self) -> bool:
        """True when every normal is exactly (0, 0, 1)."""
        return is_flat(self.normals)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "Capture":
        """Copy on ``device`` and/or with float tensors cast to ``dtype`` (bool masks stay bool)."""

        def move(t: Tensor) -> Tensor:
            return t.to(device=device, dtype=dtype if t.is_floating_point() else None)

        return Capture(
            images=move(self.images), normals=move(self.normals), mask=move(self.mask),
            lights=move(self.lights), intensities=move(self.intensities), cameras=move(self.cameras),
            size=self.size, saturated=move(self.saturated), names=list(self.names), color_space=self.color_space,
            normals_given=self.normals_given,
        )

    def subset(self, indices: Sequence[int] | Tensor | slice) -> "Capture":
        """A capture with only the shots ``indices`` (in that order)."""
        if isinstance(indices, slice):
            indices = list(range(self.num_shots))[indices]
        idx = torch.as_tensor(indices, dtype=torch.long).reshape(-1)
        if idx.numel() == 0:
            raise CaptureError("Capture.subset: expected at least one shot index, found none")
        if bool(((idx < -self.num_shots) | (idx >= self.num_shots)).any()):
            raise CaptureError(f"Capture.subset: expected indices in [0, {self.num_shots}), found {idx.tolist()}")
        idx = idx % self.num_shots
        pick = lambda t: t.index_select(0, idx.to(t.device))  # noqa: E731
        return Capture(
            images=pick(self.images), normals=self.normals, mask=self.mask, lights=pick(self.lights),
            intensities=pick(self.intensities), cameras=pick(self.cameras), size=self.size,
            saturated=pick(self.saturated), names=[self.names[i] for i in idx.tolist()],
            color_space=self.color_space, normals_given=self.normals_given,
        )

    def downsampled(self, factor: int) -> "Capture":
        """The capture box-downsampled by ``factor``: a pixel's mean colour and normal; inside the mask where its
        whole block is; saturated where any of its block is. Rows and columns beyond whole blocks are dropped,
        split between both edges, and the surface shrinks with them: each pixel's centre is its block's centre
        (within half a pixel of the capture's where an odd number of rows or columns is dropped)."""
        if factor <= 1:
            return self
        h, w = self.height // factor, self.width // factor
        r0, c0 = (self.height - h * factor) // 2, (self.width - w * factor) // 2
        crop = lambda t: t[..., r0 : r0 + h * factor, c0 : c0 + w * factor]  # noqa: E731
        pool = torch.nn.functional.avg_pool2d
        images = pool(crop(self.images), factor)
        mask = pool(crop(self.mask).double().unsqueeze(0), factor)[0] > 1.0 - 1e-9
        saturated = torch.nn.functional.max_pool2d(crop(self.saturated).to(images.dtype), factor) > 0
        normals = torch.nn.functional.normalize(pool(crop(self.normals).unsqueeze(0), factor)[0], dim=0)
        return Capture(
            images=images, normals=None if self.flat and not self.normals_given else normals, mask=mask,
            lights=self.lights, intensities=self.intensities, cameras=self.cameras,
            size=(self.size[0] * w * factor / self.width, self.size[1] * h * factor / self.height),
            saturated=saturated, names=list(self.names), color_space=self.color_space,
            normals_given=self.normals_given,
        )

    def __repr__(self) -> str:
        kinds = {0.0: "directional", 1.0: "point"}
        lights = sorted({kinds.get(float(w), "?") for w in self.lights[:, 3].tolist()})
        return (
            f"Capture({self.num_shots} shots, {self.height}x{self.width}, {self.images.dtype}, "
            f"{self.images.device}, source {self.color_space}, size={self.size}, lights={'/'.join(lights)}, "
            f"flat={self.flat}, mask={int(self.mask.sum())}/{self.height * self.width} px, "
            f"saturated={float(self.saturated.float().mean()):.2%})"
        )


# -------------------------------------------------------------------------------- loading


@dataclass
class _Shot:
    image: str
    light: list[float]
    intensity: list[float]
    camera: list[float]


def read_meta(meta_file: Path) -> dict:
    if not meta_file.is_file():
        raise CaptureError(f"{meta_file}: expected a capture description file, found nothing")
    try:
        return json.loads(meta_file.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise CaptureError(f"{meta_file}: expected valid JSON, found a syntax error at line {e.lineno} column {e.colno} ({e.msg})") from None
    except UnicodeDecodeError as e:
        raise CaptureError(f"{meta_file}: expected UTF-8 JSON text, found undecodable bytes at offset {e.start}") from None
    except OSError as e:
        raise CaptureError(f"{meta_file}: expected a readable file, found {e.strerror or e}") from None


def parse_meta(meta: object, label: str) -> tuple[str, tuple[float, float], str | None, str | None, str | None, list[_Shot]]:
    if not isinstance(meta, dict):
        raise CaptureError(f"{label}: expected a JSON object, found {type(meta).__name__}")
    if "format" not in meta:
        raise CaptureError(f"{label}: expected \"format\": {FORMAT!r}, found no format key")
    if meta["format"] != FORMAT:
        raise CaptureError(f"{label}: expected format {FORMAT!r}, found {short_repr(meta['format'])}")
    if meta.get("version") != VERSION or isinstance(meta.get("version"), bool):
        raise CaptureError(f"{label}: expected version {VERSION}, found {short_repr(meta.get('version'))} (unsupported)")
    missing = [k for k in _TOP_KEYS if k not in meta]
    if missing:
        raise CaptureError(f"{label}: expected keys {list(_TOP_KEYS)}, missing {missing}")
    cs = meta["color_space"]
    if cs not in COLOR_SPACES:
        raise CaptureError(f"{label}: color_space: expected one of {list(COLOR_SPACES)}, found {short_repr(cs)}")
    surf = meta["surface"]
    if not isinstance(surf, dict) or "width" not in surf or "height" not in surf:
        raise CaptureError(f"{label}: surface: expected {{\"width\": w, \"height\": h}}, found {short_repr(surf)}")
    size = check_size((surf["width"], surf["height"]), f"{label}: surface width/height")
    opt: dict[str, str | None] = {}
    for key in ("normals", "mask", "saturated"):
        v = meta.get(key)
        if v is not None and (not isinstance(v, str) or not v):
            raise CaptureError(f"{label}: {key}: expected a file name or null, found {short_repr(v)}")
        opt[key] = v
    raw = meta["shots"]
    if not isinstance(raw, list):
        raise CaptureError(f"{label}: shots: expected a list of shots, found {type(raw).__name__}")
    if not raw:
        raise CaptureError(f"{label}: shots: expected at least 1 shot, found 0")
    shots = []
    for k, s in enumerate(raw):
        where = f"{label}: shots[{k}]"
        if not isinstance(s, dict):
            raise CaptureError(f"{where}: expected an object with keys {list(_SHOT_KEYS)}, found {type(s).__name__}")
        lost = [key for key in _SHOT_KEYS if key not in s]
        if lost:
            raise CaptureError(f"{where}: expected keys {list(_SHOT_KEYS)}, missing {lost}")
        if not isinstance(s["image"], str) or not s["image"]:
            raise CaptureError(f"{where}.image: expected a file name, found {short_repr(s['image'])}")
        light = numbers(s["light"], 4, f"{where}.light")
        check_light(light, f"{where}.light")
        inten = numbers(s["light_intensity"], 3, f"{where}.light_intensity")
        check_intensity(inten, f"{where}.light_intensity")
        cam = numbers(s["camera"], 4, f"{where}.camera")
        check_camera(cam, f"{where}.camera")
        shots.append(_Shot(s["image"], light, inten, cam))
    return cs, size, opt["normals"], opt["mask"], opt["saturated"], shots


def _load_npy(f: Path, what: str) -> np.ndarray:
    if not f.is_file():
        raise CaptureError(f"{f}: expected the {what} file named in capture.json, found nothing")
    try:
        return np.load(f, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise CaptureError(f"{f}: expected a numpy .npy array, found unreadable data ({e})") from None


def _load_normals(f: Path, h: int, w: int) -> Tensor:
    arr = _load_npy(f, "normals")
    if arr.shape != (h, w, 3):
        raise CaptureError(f"{f}: expected shape (H, W, 3) = {(h, w, 3)}, found {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise CaptureError(f"{f}: expected float normals, found dtype {arr.dtype}")
    n = np.asarray(arr, dtype=np.float64)
    bad = ~np.isfinite(n).all(axis=2)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise CaptureError(f"{f}: expected finite normals, found {int(bad.sum())} non-finite (first at row {i}, col {j})")
    with np.errstate(over="ignore"):
        length = np.sqrt((n * n).sum(axis=2, keepdims=True))
    if not np.isfinite(length).all():  # components near the float64 limit: the length of n / max |n_i|
        big = np.abs(n).max(axis=2, keepdims=True)
        length = big * np.sqrt(((n / big) ** 2).sum(axis=2, keepdims=True))
    zero = length[..., 0] < 1e-12
    if zero.any():
        i, j = np.argwhere(zero)[0]
        raise CaptureError(f"{f}: expected non-zero normals, found {int(zero.sum())} zero-length (first at row {i}, col {j})")
    off = np.abs(length - 1.0) > UNIT_TOL  # leave unit vectors bit-exact, normalise the rest
    out = np.where(off, n / length, n).astype(np.float32)
    return torch.from_numpy(np.ascontiguousarray(out.transpose(2, 0, 1)))


def load_mask(f: Path, h: int, w: int) -> Tensor:
    if f.suffix.lower() == ".npy":
        arr = _load_npy(f, "mask")
    else:
        if not f.is_file():
            raise CaptureError(f"{f}: expected the mask file named in capture.json, found nothing")
        data = np.fromfile(f, dtype=np.uint8)
        cv2 = _cv2()
        arr = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if arr is None:
            raise CaptureError(f"{f}: expected a readable mask image, found undecodable data")
    if arr.ndim == 3:
        arr = arr[:, :, :3] if arr.shape[2] == 4 else arr
        arr = (arr != 0).any(axis=2)
    if arr.ndim != 2 or arr.shape != (h, w):
        raise CaptureError(f"{f}: expected a mask of size {w}x{h} (width x height), found shape {arr.shape}")
    return torch.from_numpy(np.ascontiguousarray(arr != 0)).unsqueeze(0)


def _load_saturated(f: Path, n: int, h: int, w: int) -> Tensor:
    arr = _load_npy(f, "saturated")
    if arr.shape != (n, h, w, 3) or arr.dtype != np.bool_:
        raise CaptureError(f"{f}: expected a bool array of shape {(n, h, w, 3)}, found {arr.dtype} {arr.shape}")
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(0, 3, 1, 2)))


def _read_images(root: Path, shots: list[_Shot], color_space: str) -> tuple[Tensor, Tensor, list[float]]:
    """The shots' images (N, 3, H, W) float32 linear, their saturation (N, 3, H, W) bool and each shot's
    brightest linear value. The files are decoded one ahead, in a thread (the decoders release the GIL), while
    the previous one is converted: at most two raw images are held."""
    n = len(shots)
    with ThreadPoolExecutor(max_workers=1) as pool:
        ahead = pool.submit(read_raw, root / shots[0].image)
        first = ahead.result()
        h, w = first.shape[:2]
        images = torch.empty((n, 3, h, w), dtype=torch.float32)  # the only full-size allocation
        saturated = torch.empty((n, 3, h, w), dtype=torch.bool)
        images_np, saturated_np = images.numpy(), saturated.numpy()  # shared memory views
        peaks: list[float] = []  # each shot's brightest linear value
        for k, shot in enumerate(shots):
            f = root / shot.image
            raw = first if k == 0 else ahead.result()
            ahead = pool.submit(read_raw, root / shots[k + 1].image) if k + 1 < n else None
            if raw.shape[:2] != (h, w):
                raise CaptureError(
                    f"{f}: expected size {w}x{h} (width x height, as {shots[0].image}), found {raw.shape[1]}x{raw.shape[0]}"
                )
            peaks.append(_decode_shot(raw, images, saturated, images_np, saturated_np, k, f, color_space))
            del raw
        del first
    return images, saturated, peaks


def _decode_shot(raw: np.ndarray, images: Tensor, saturated: Tensor, images_np: np.ndarray, saturated_np: np.ndarray,
                 k: int, f: Path, color_space: str) -> float:
    """Shot ``k``'s raw file values into ``images[k]`` (linear) and ``saturated[k]``; returns its brightest linear value."""
    is_float = raw.dtype.kind == "f"
    # integer codes go through the lookup table (sRGB included); floats are checked as stored
    decode_planes(raw, images_np[k], saturated_np[k], srgb=color_space == "srgb" and not is_float)
    if not is_float:  # the tables increase with the code: the brightest pixel is the largest code's value
        return float(code_table(8 if raw.dtype == np.uint8 else 16, color_space == "srgb")[raw.max()])
    peak = check_pixels(images[k], str(f))  # integer files are finite and >= 0 by construction
    if color_space == "srgb":
        images[k] = srgb_to_linear(images[k])
        peak = float(srgb_to_linear(torch.tensor(peak, dtype=torch.float64)))
    return peak


def load_capture(path: str | os.PathLike) -> Capture:
    """Read a capture directory (docs/design.md §2.1).

    Images are read one at a time into a preallocated (N, 3, H, W) float32 tensor. 8/16-bit
    files are decoded straight from their integer codes by lookup table (for sRGB, the curve
    evaluated in float64 and rounded once to float32); float sRGB files with
    :func:`srgb_to_linear`. Saturation comes from the raw values (255 / 65535
    for PNG; none for float files, unless the capture carries ``saturated.npy``).

    Args:
        path: the capture directory, or its capture.json.

    Raises:
        CaptureError: anything missing, malformed or physically impossible, in one line.
    """
    root = Path(path)
    meta_file = root if root.suffix.lower() == ".json" and not root.is_dir() else root / "capture.json"
    root = meta_file.parent
    color_space, size, normals_name, mask_name, sat_name, shots = parse_meta(read_meta(meta_file), str(meta_file))

    n = len(shots)
    images, saturated, peaks = _read_images(root, shots, color_space)
    h, w = images.shape[-2:]

    normals = _load_normals(root / normals_name, h, w) if normals_name else None
    mask = load_mask(root / mask_name, h, w) if mask_name else None
    if sat_name:
        saturated |= _load_saturated(root / sat_name, n, h, w)

    f32 = lambda rows: torch.tensor(rows, dtype=torch.float64).to(torch.float32)  # noqa: E731
    lights, intensities, cameras = (f32([getattr(s, a) for s in shots]) for a in ("light", "intensity", "camera"))
    labels = [f"{meta_file}: shots[{k}] ({s.image})" for k, s in enumerate(shots)]
    # again in float32 (a z of 1e-300 is 0 there), and each photo against its light, naming this file
    check_light_camera(lights, intensities, cameras, error=CaptureError, labels=labels)
    check_exposure(peaks, lights, intensities, size, labels)
    cap = Capture(
        images=images, normals=normals, mask=mask, lights=lights, intensities=intensities,
        cameras=cameras, size=size, saturated=saturated,
        names=[s.image for s in shots], color_space=color_space,
    )
    if is_large(cap):  # the decoders' buffers and the checks' temporaries
        release_free_memory()
    return cap
