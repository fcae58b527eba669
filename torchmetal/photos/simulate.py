"""Generated "phone photos" of a known material in the board's window, with the truth behind them.

A perspective camera with known intrinsics and radial distortion looks at the printed sheet
from hand-held poses; the flash sits at a known offset from the lens. Every photo pixel is
traced (``supersample``² rays through the distorted lens) to the sheet plane and shaded with
torchmetal's own forward model (:func:`torchmetal.geometry.shading_geometry` +
:func:`torchmetal.phong.phong_shading`): the sample (texture, s, α) inside the window, the
printed sheet (Lambertian paper and ink) around it. The linear image is scaled by the photo's
exposure (EXIF time × ISO / f-number², written into the file) and an auto-white-balance tint,
gets shot and read noise, and is stored as an sRGB 8-bit JPEG. Options for what real photos do
to the white reference: a flash hotspot on the paper (:class:`Hotspot`, clipped where it is
bright) and photos written without any EXIF (``strip_exif``).

The truth (:class:`PhotoSet`) gives what a perfect capture would hold: intrinsics, poses,
camera and flash positions in the capture frame, and the light intensity in pixel units, so
:func:`direct_render` renders the clean reference images on the capture grid.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchmetal.geometry import shading_geometry
from torchmetal.io.capture import Capture
from torchmetal.io.images import atomic_write_bytes, linear_to_srgb
from torchmetal.phong import phong_render, phong_shading
from torchmetal.photos.board import Board, render_sheet
from torchmetal.photos.calibrate import Intrinsics, camera_position, flash_position
from torchmetal.photos.exif import PhotoExif, exif_bytes

__all__ = ["Sample", "PhotoSet", "Hotspot", "smooth_texture", "phone_camera", "hand_held_poses", "render_photo", "phone_photos",
           "direct_render", "truth_capture"]

PAPER_ALBEDO = 0.85  # printer paper
INK_ALBEDO = 0.03
TABLE_ALBEDO = 0.12  # what lies around the sheet
TARGET_PAPER = 0.55  # the auto exposure puts the paper near this linear level
F_NUMBER = 1.8
GAIN = 0.1  # photo value per unit radiance and unit exposure (t · ISO / N²)


@dataclass
class Sample:
    """The material in the window: texture (3, H, W) linear on the window grid (docs/design.md §2.1
    pixel geometry over the window), per-channel s (3,) and α (3,)."""

    texture: torch.Tensor
    s: torch.Tensor
    alpha: torch.Tensor


@dataclass(frozen=True)
class Hotspot:
    """A flash hotspot on the printed sheet (glossy paper): outside the window, the sheet's radiance
    is multiplied by 1 + ``peak`` · exp(−r² / 2σ²), r the distance on the sheet from ``centre_mm``
    (capture frame: mm from the window centre, x right, y up), σ = ``sigma_mm``. With the paper
    near 0.55 of full scale, ``peak`` 4 clips it out to r ≈ 1.8 σ; a huge σ brightens the whole sheet.
    The sample in the window is untouched (its truth stays the model's)."""

    centre_mm: tuple[float, float] = (27.0, 0.0)
    sigma_mm: float = 4.0
    peak: float = 4.0


@dataclass
class PhotoSet:
    """Generated photos and their truth (capture frame: metres; board frame: mm)."""

    paths: list[Path]
    board: Board
    sample: Sample
    intrinsics: Intrinsics
    poses: list[tuple[np.ndarray, np.ndarray]]  # (rvec, tvec) board → camera, mm
    cameras: np.ndarray  # (N, 3) capture frame, m
    lights: np.ndarray  # (N, 3) capture frame, m
    intensity: np.ndarray  # (N,) flash intensity in photo pixel units (flash power × gain)
    exif: list[PhotoExif] = field(default_factory=list)
    tints: np.ndarray | None = None  # (N, 3) the auto white balance's gains on each photo


def smooth_texture(h: int, w: int, seed: int = 0, lo: float = 0.08, hi: float = 0.6) -> torch.Tensor:
    """(3, H, W) float32 colour texture in [lo, hi]: two octaves of smooth (bicubic) noise."""
    import torch.nn.functional as F

    g = torch.Generator().manual_seed(seed)
    out = torch.zeros(1, 3, h, w, dtype=torch.float64)
    for cells, amp in ((3, 1.0), (9, 0.45)):
        base = torch.rand(1, 3, cells + 3, cells + 3, generator=g, dtype=torch.float64)
        up = F.interpolate(base, size=(h + 2 * h // cells, w + 2 * w // cells), mode="bicubic", align_corners=False)
        out += amp * up[:, :, h // cells: h // cells + h, w // cells: w // cells + w]
    out = (out - out.amin()) / (out.amax() - out.amin())
    return (lo + (hi - lo) * out[0]).float()


def phone_camera(size: tuple[int, int] = (800, 600), hfov_deg: float = 64.0, k1: float = 0.08, k2: float = -0.06,
                 shift: tuple[float, float] = (0.011, -0.008)) -> Intrinsics:
    """A phone-like camera: fx = fy from the horizontal field of view, principal point shifted by
    ``shift`` × size from the centre, radial distortion k1, k2."""
    w, h = size
    f = 0.5 * w / math.tan(math.radians(hfov_deg) / 2)
    k = np.array([[f, 0, (w - 1) / 2 + shift[0] * w], [0, f, (h - 1) / 2 + shift[1] * h], [0, 0, 1]], np.float64)
    return Intrinsics((w, h), k, np.array([k1, k2, 0, 0, 0], np.float64), 0.0, "truth", "Generated Phone")


def _look_at(board: Board, centre: np.ndarray, target: np.ndarray, roll: float) -> tuple[np.ndarray, np.ndarray]:
    """(rvec, tvec) of a camera at ``centre`` looking at ``target`` (capture frame, m), image
    'down' towards the photographer, rolled by ``roll`` radians."""
    import cv2

    z = target - centre
    z /= np.linalg.norm(z)
    towards = np.array([centre[0], centre[1], 0.0])
    if np.linalg.norm(towards) < 1e-9:
        towards = np.array([0.0, -1.0, 0.0])
    y = towards - (towards @ z) * z
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    c, s = math.cos(roll), math.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    r_cap = np.stack([x, y, z], 1)  # camera → capture frame (columns)
    m = np.diag([1.0, -1.0, -1.0])  # capture → board axes
    r_board = m @ r_cap  # camera → board
    rot = r_board.T  # board → camera
    c_board = board.capture_to_board(centre)
    tvec = -rot @ c_board
    return cv2.Rodrigues(rot)[0].ravel(), tvec


def hand_held_poses(board: Board, n: int = 12, seed: int = 0, *, elevation: tuple[float, float] = (25.0, 70.0),
                    overhead: int = 3, distance: tuple[float, float] = (0.27, 0.33)) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` hand-held poses around the window: elevations spread over ``elevation`` (degrees) plus
    ``overhead`` near-overhead ones (80–87°, so the flash highlight lands in the window),
    azimuths all round, distance ``distance`` (m) from the window centre, aim within ±6 mm of it,
    roll ±15°."""
    rng = np.random.default_rng(seed)
    k = n - overhead
    els = list(np.linspace(*elevation, k) + rng.uniform(-2, 2, k)) if k > 0 else []
    els = [float(np.clip(e, *elevation)) for e in els] + list(rng.uniform(80, 87, overhead))
    azs = (np.arange(n) * 137.5 + rng.uniform(0, 360)) % 360
    poses = []
    for el, az in zip(els, azs):
        d = rng.uniform(*distance)
        e, a = math.radians(el), math.radians(az)
        centre = d * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
        target = np.array([*rng.uniform(-0.006, 0.006, 2), 0.0])
        poses.append(_look_at(board, centre, target, math.radians(rng.uniform(-15, 15))))
    return poses


def _undistort(px: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Normalised ideal coordinates (n, 2) of distorted pixels (n, 2): the radial model
    r_d = r·(1 + k1·r² + k2·r⁴) inverted by Newton's method to machine precision."""
    k1, k2, p1, p2, k3 = intr.distortion
    if p1 or p2 or k3:
        raise ValueError("the photo generator models radial distortion k1, k2 only")
    k = intr.matrix
    xd = (px[:, 0] - k[0, 2]) / k[0, 0]
    yd = (px[:, 1] - k[1, 2]) / k[1, 1]
    rd = np.hypot(xd, yd)
    r = rd.copy()
    for _ in range(30):
        r2 = r * r
        g = r * (1 + k1 * r2 + k2 * r2 * r2) - rd
        r -= g / (1 + 3 * k1 * r2 + 5 * k2 * r2 * r2)
        if float(np.abs(g).max()) < 1e-15:
            break
    scale = np.where(rd > 0, r / np.where(rd > 0, rd, 1), 1.0)
    return np.stack([xd * scale, yd * scale], 1)


_RAY_CACHE: dict = {}


def _camera_rays(intr: Intrinsics, supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """x', y' (h·ss·w·ss,) float64 of the camera-frame rays (x', y', 1) through every sub-pixel
    (cached for the last camera)."""
    key = (intr.image_size, intr.matrix.tobytes(), intr.distortion.tobytes(), supersample)
    if key not in _RAY_CACHE:
        w, h = intr.image_size
        off = (np.arange(supersample) + 0.5) / supersample - 0.5
        xs = (np.arange(w)[:, None] + off[None, :]).ravel()
        ys = (np.arange(h)[:, None] + off[None, :]).ravel()
        gx, gy = np.meshgrid(xs, ys)
        und = _undistort(np.stack([gx.ravel(), gy.ravel()], 1), intr)
        _RAY_CACHE.clear()
        _RAY_CACHE[key] = (np.ascontiguousarray(und[:, 0]), np.ascontiguousarray(und[:, 1]))
    return _RAY_CACHE[key]


def _rays(intr: Intrinsics, rvec, tvec, supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """Board-plane hits (n, 2) mm of the rays through every sub-pixel (row-major over the
    (h·ss, w·ss) grid), and a hit mask (n,)."""
    import cv2

    rot = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))[0]
    centre = -rot.T @ np.asarray(tvec, np.float64)
    x, y = _camera_rays(intr, supersample)
    d = [x * rot[0, k] + y * rot[1, k] + rot[2, k] for k in range(3)]  # R^T [x, y, 1], by columns
    t = -centre[2] / np.where(np.abs(d[2]) < 1e-12, 1e-12, d[2])
    return np.stack([centre[0] + t * d[0], centre[1] + t * d[1]], 1), t > 0


def _lookup(img: np.ndarray, x: np.ndarray, y: np.ndarray, border: float | None) -> np.ndarray:
    """Bilinear values of ``img`` (H, W[, C]) at pixel coordinates x, y (n,): (n[, C]). Outside:
    ``border``, or the nearest edge value when None."""
    import cv2

    n = x.size
    cols = 4096
    rows = -(-n // cols)
    pad = rows * cols - n
    mx = np.concatenate([x, np.zeros(pad)]).astype(np.float32).reshape(rows, cols)
    my = np.concatenate([y, np.zeros(pad)]).astype(np.float32).reshape(rows, cols)
    mode = cv2.BORDER_REPLICATE if border is None else cv2.BORDER_CONSTANT
    out = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=mode, borderValue=0.0 if border is None else border)
    return out.reshape(rows * cols, *img.shape[2:])[:n]


def render_photo(board: Board, sheet: np.ndarray, sample: Sample, intr: Intrinsics, pose, light: np.ndarray,
                 intensity: float, *, supersample: int = 2, hotspot: Hotspot | None = None) -> np.ndarray:
    """Linear radiance (h, w, 3) float32 of one photo (before exposure gain, tint and noise).

    ``sheet``: (Hs, Ws) reflectance of the print (1 = paper) at ``board.dpi``; ``light``: the
    flash (3,) in the capture frame (m); ``intensity``: its radiant intensity. The sample is
    shaded by :func:`~torchmetal.phong.phong_shading`, the sheet (paper, ink) and the table
    around it as Lambertian surfaces; ``hotspot`` brightens the sheet around a point.
    """
    import cv2

    rvec, tvec = pose
    w, h = intr.image_size
    ss = supersample
    p, hit = _rays(intr, rvec, tvec, ss)
    ox, oy = board.origin_mm
    px = board.dpi / 25.4
    refl = _lookup(sheet.astype(np.float32), (p[:, 0] + ox) * px - 0.5, (p[:, 1] + oy) * px - 0.5, border=-1.0)
    albedo = np.where(refl < 0, TABLE_ALBEDO, INK_ALBEDO + (PAPER_ALBEDO - INK_ALBEDO) * np.clip(refl, 0, 1)).astype(np.float32)
    q = board.board_to_capture(np.concatenate([p, np.zeros((len(p), 1))], 1)).astype(np.float32)  # (n, 3) m
    lv = np.asarray(light, np.float32)[None] - q
    d2 = (lv * lv).sum(1)
    lambert = intensity * np.clip(lv[:, 2], 0, None) / (d2 * np.sqrt(d2))
    rad = (albedo * lambert)[:, None] * np.ones((1, 3), np.float32)
    if hotspot is not None:
        r2 = ((q[:, 0] * 1000 - hotspot.centre_mm[0]) ** 2 + (q[:, 1] * 1000 - hotspot.centre_mm[1]) ** 2)
        rad *= (1 + hotspot.peak * np.exp(-r2 / (2 * hotspot.sigma_mm**2)))[:, None].astype(np.float32)
    # the sample: torchmetal's Phong model at the plane points inside the window
    cx, cy = board.window_centre_board
    wmm, hmm = board.window_size_mm
    X, Y = p[:, 0] - cx, cy - p[:, 1]
    idx = np.flatnonzero((np.abs(X) < wmm / 2) & (np.abs(Y) < hmm / 2) & hit)
    if idx.size:
        _, th, tw = sample.texture.shape
        tex_hwc = np.ascontiguousarray(sample.texture.permute(1, 2, 0).float().numpy())
        tex = _lookup(tex_hwc, (X[idx] / wmm + 0.5) * tw - 0.5, (0.5 - Y[idx] / hmm) * th - 0.5, border=None)
        pts = torch.from_numpy(np.ascontiguousarray(q[idx].T)).unsqueeze(-1)  # (3, m, 1)
        normals = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, idx.size, 1)
        lt = torch.tensor([[*light, 1.0]], dtype=torch.float32)
        cam = torch.tensor([[*board.board_to_capture(-cv2.Rodrigues(rvec)[0].T @ tvec), 1.0]], dtype=torch.float32)
        geom = shading_geometry(normals, lt, torch.full((1, 3), float(intensity)), cam, points=pts)
        shade = phong_shading(torch.from_numpy(np.ascontiguousarray(tex.T)).unsqueeze(-1), sample.s.float(),
                              sample.alpha.float(), geom)
        rad[idx] = shade[0, :, :, 0].T.numpy()
    rad[~hit] = 0.0
    img = rad.reshape(h, ss, w, ss, 3).mean((1, 3))
    return np.ascontiguousarray(img, dtype=np.float32)


def _encode_jpeg(linear: np.ndarray, quality: int, exif: PhotoExif | None) -> bytes:
    import io

    from PIL import Image

    code = np.rint(linear_to_srgb(torch.from_numpy(np.clip(linear, 0, 1))).numpy() * 255).astype(np.uint8)
    buf = io.BytesIO()
    extra = {} if exif is None else {"exif": exif_bytes(exif)}
    Image.fromarray(code, "RGB").save(buf, "JPEG", quality=quality, subsampling=0, **extra)
    return buf.getvalue()


def phone_photos(out_dir: str | os.PathLike, board: Board, sample: Sample, *, n: int = 12, seed: int = 0,
                 camera: Intrinsics | None = None, poses=None, flash_offset_mm=(12.0, -4.0, 0.0), noise: float = 0.01,
                 quality: int = 92, supersample: int = 2, tint: float = 0.08, sheet: np.ndarray | None = None,
                 names: list[str] | None = None, exif: list[PhotoExif | None] | None = None,
                 hotspots: dict[int, Hotspot] | None = None, strip_exif=()) -> PhotoSet:
    """Write ``n`` generated JPEG photos into ``out_dir``; returns them with their truth.

    Args:
        camera: intrinsics (default :func:`phone_camera`); poses: (rvec, tvec) list (default
            :func:`hand_held_poses`); flash_offset_mm: the flash in the camera frame.
        noise: shot-noise level (σ = noise·√(v/0.5) at linear value v, plus a read noise of noise/4).
        tint: spread of the per-photo white-balance gains on red and blue.
        exif: per photo, the EXIF to write instead of the true one (None entries: the truth).
        hotspots: {photo index: :class:`Hotspot`}, a flash hotspot on the sheet of those photos.
        strip_exif: indices of photos written without any EXIF block (the truth keeps their exposure).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    camera = camera or phone_camera()
    poses = poses if poses is not None else hand_held_poses(board, n, seed)
    n = len(poses)
    sheet = render_sheet(board) if sheet is None else sheet
    rng = np.random.default_rng(seed + 1000)
    paths, cams, lights, inten, exifs, tints = [], [], [], [], [], []
    for k, pose in enumerate(poses):
        c = camera_position(board, *pose)
        light = flash_position(board, *pose, flash_offset_mm)
        cos = light[2] / np.linalg.norm(light)
        e_paper = cos / float(light @ light)  # irradiance per unit intensity at the window centre
        # auto exposure: ISO chosen so that the paper lands near TARGET_PAPER at 1/60 s, f/1.8
        t = 1 / 60
        iso = float(np.clip(round(TARGET_PAPER / (PAPER_ALBEDO * e_paper) / (GAIN * t / F_NUMBER**2)), 25, 3200))
        ex = PhotoExif(exposure_time=t, f_number=F_NUMBER, iso=iso, make="Generated", model="Phone",
                       focal_mm=4.25)
        gain = GAIN * ex.exposure  # photo value per unit radiance
        rad = render_photo(board, sheet, sample, camera, pose, light, 1.0, supersample=supersample,
                           hotspot=(hotspots or {}).get(k))
        wb = np.array([1 + rng.uniform(-tint, tint), 1.0, 1 + rng.uniform(-tint, tint)])
        v = rad * gain * wb
        sigma = np.sqrt(noise**2 * np.clip(v, 0, None) / 0.5 + (noise / 4) ** 2)
        v = v + sigma * rng.standard_normal(v.shape)
        written = None if k in strip_exif else ex if exif is None or exif[k] is None else exif[k]
        name = names[k] if names else f"IMG_{k + 1:04d}.jpg"
        path = out / name
        atomic_write_bytes(path, _encode_jpeg(v, quality, written))
        paths.append(path)
        cams.append(c)
        lights.append(light)
        inten.append(gain)
        exifs.append(ex)
        tints.append(wb)
    return PhotoSet(paths, board, sample, camera, list(poses), np.array(cams), np.array(lights), np.array(inten), exifs,
                    np.array(tints))


def direct_render(photos: PhotoSet, indices=None) -> torch.Tensor:
    """Clean renders (N, 3, H, W) of the sample at the true geometry on the texture's own grid
    (the capture grid when the capture's resolution matches the texture), in photo pixel units."""
    idx = range(len(photos.paths)) if indices is None else indices
    tex = photos.sample.texture.float()
    _, h, w = tex.shape
    normals = torch.zeros(3, h, w)
    normals[2] = 1
    ww, wh = photos.board.window_size_mm
    lights = torch.tensor([[*photos.lights[k], 1.0] for k in idx], dtype=torch.float32)
    cams = torch.tensor([[*photos.cameras[k], 1.0] for k in idx], dtype=torch.float32)
    inten = torch.tensor([[photos.intensity[k]] * 3 for k in idx], dtype=torch.float32)
    return phong_render(tex, photos.sample.s.float(), photos.sample.alpha.float(), normals, lights, inten, cams,
                        (ww / 1000, wh / 1000))


def truth_capture(photos: PhotoSet, indices=None):
    """A directly rendered capture: the clean renders at the true geometry (the reference fit)."""
    idx = list(range(len(photos.paths)) if indices is None else indices)
    ww, wh = photos.board.window_size_mm
    return Capture(
        images=direct_render(photos, idx),
        lights=torch.tensor([[*photos.lights[k], 1.0] for k in idx], dtype=torch.float32),
        intensities=torch.tensor([[photos.intensity[k]] * 3 for k in idx], dtype=torch.float32),
        cameras=torch.tensor([[*photos.cameras[k], 1.0] for k in idx], dtype=torch.float32),
        size=(ww / 1000, wh / 1000), names=[photos.paths[k].stem for k in idx],
    )
