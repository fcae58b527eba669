"""Synthetic captures with known ground truth (for tests, demos and benchmarks).

:func:`synth_capture` renders a Phong material (docs/design.md §2.2), optionally with spatially varying
specular clusters, bumpy normals and metallic flakes, under one of a few light layouts, and
returns the :class:`~torchmetal.io.capture.Capture` together with the truth that made it.
Everything is drawn from seeded ``torch.Generator`` s (one per ingredient, so switching one
option on does not reshuffle the others) — the same arguments give bit-identical tensors.

Scene: a 0.1 × 0.1 surface (metres) at z = 0, perspective cameras (w = 1) near (0, 0, 0.3)
that move a little from shot to shot. Layouts:

=============  =========================================================================
``ring``       point lights at z = 0.25 around the camera; each shot's mirror highlight
               lies on a ring of radius 0.025 on the sample
``hemisphere`` point lights at z ∈ [0.1, 0.5], highlight anywhere within 0.035 of the centre
``near``       point lights at z ∈ [0.04, 0.08] (strong fall-off), highlight on the sample
``far``        directional lights (w = 0), elevation 35°–88° (highlights only for the
               steep ones)
``grazing``    directional lights (w = 0), elevation 5°–15° (no mirror highlight)
=============  =========================================================================

Intensities are set so that the mean diffuse level over the sample is ≈ 0.25·``exposure``
(times a per-shot factor in [0.85, 1.15]); highlights add up to ≈ 0.6, so 8/16-bit quantisation
clips a little (bright texture under a highlight), as real captures do.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from torchmetal.errors import CaptureError, InputError
from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.model.field import flake_field, sparkle_render
from torchmetal.geometry import surface_points
from torchmetal.io.capture import Capture
from torchmetal.io.capture_save import prepare_target, replace_dir, write_capture_files
from torchmetal.io.images import PNG_MAX, atomic_write_bytes, srgb_to_linear
from torchmetal.material import Material
from torchmetal.phong import phong_render

__all__ = ["SynthResult", "synth_capture", "write_synth", "read_synth_truth", "LAYOUTS", "SURFACE", "CAMERA_HEIGHT"]

LAYOUTS = ("ring", "hemisphere", "near", "far", "grazing")
TEXTURES = ("auto", "procedural", "photo")
PHOTOS = ("astronaut", "coffee", "chelsea")
SURFACE = (0.1, 0.1)  # (width, height), metres
CAMERA_HEIGHT = 0.3
TEXTURE_RANGE = (0.05, 0.7)
DIFFUSE_LEVEL = 0.25
TRUTH_FORMAT = "torchmetal-synth-truth"

# one generator stream per ingredient
_TEXTURE, _NORMALS, _CLUSTERS, _GEOMETRY, _NOISE = range(5)


@dataclass
class SynthResult:
    """A synthetic capture and the truth that rendered it.

    ``truth`` keys: ``texture`` (3, H, W); ``s``, ``alpha`` (3,) (area-weighted cluster means
    when clustered); ``normals`` (3, H, W); ``flakes`` (FlakeModel or None); ``flake_field``
    (FlakeField or None); and with ``spec_clusters`` ≥ 2: ``spec_labels`` (H, W) int64,
    ``cluster_s``, ``cluster_alpha`` (K, 3). ``params``: the JSON-able arguments.
    """

    capture: Capture
    truth: dict
    params: dict = field(default_factory=dict)

    def specular_maps(self) -> tuple[Tensor, Tensor]:
        """s and α as (3,) globals or, when clustered, (3, H, W) maps."""
        t = self.truth
        if t.get("spec_labels") is None:
            return t["s"], t["alpha"]
        lab = t["spec_labels"]
        return t["cluster_s"][lab].permute(2, 0, 1), t["cluster_alpha"][lab].permute(2, 0, 1)

    def render_clean(self, indices: slice | list[int] | None = None) -> Tensor:
        """Noise-free, unquantised images of the truth, (N, 3, H, W) (a shot subset if given)."""
        c = self.capture if indices is None else self.capture.subset(indices)
        return _render(self.truth, self.specular_maps(), c.normals, c.lights, c.intensities, c.cameras, c.size)

    def material(self) -> Material:
        """The truth as a :class:`torchmetal.material.Material` (for comparing fits)."""
        t = self.truth
        flat = self.capture.flat
        return Material(
            t["texture"], t["s"], t["alpha"], self.capture.size, None if flat else t["normals"],
            t.get("spec_labels"), t.get("cluster_s"), t.get("cluster_alpha"), t["flakes"],
            {"source": "synth", "params": dict(self.params)},
        )


# ------------------------------------------------------------------------------- ingredients


def _generator(seed: int, stream: int) -> torch.Generator:
    return torch.Generator().manual_seed((int(seed) * 1_000_003 + stream * 7_919 + 17) % (2**63))


def _smooth_noise(g: torch.Generator, channels: int, h: int, w: int, cells: int) -> Tensor:
    """(channels, H, W) float64 smooth noise, about [0, 1]: a random (cells+1)² lattice, bicubic."""
    low = torch.rand(1, channels, cells + 1, cells + 1, generator=g, dtype=torch.float64)
    return F.interpolate(low, size=(h, w), mode="bicubic", align_corners=True)[0]


def _rescale(t: Tensor) -> Tensor:
    lo, hi = TEXTURE_RANGE
    t = (t - t.min()) / (t.max() - t.min()).clamp_min(1e-12)
    return lo + (hi - lo) * t


def procedural_texture(h: int, w: int, g: torch.Generator) -> Tensor:
    """(3, H, W) float64 texture in [0.05, 0.7]: two scales of colour noise plus flat shapes."""
    base = torch.rand(3, 1, 1, generator=g, dtype=torch.float64) * 0.5 + 0.25
    tex = base + 0.35 * (_smooth_noise(g, 3, h, w, 4) - 0.5) + 0.12 * (_smooth_noise(g, 3, h, w, 16) - 0.5)
    yy = (torch.arange(h, dtype=torch.float64).view(-1, 1) + 0.5) / h
    xx = (torch.arange(w, dtype=torch.float64).view(1, -1) + 0.5) / w
    n_shapes = int(torch.randint(3, 7, (1,), generator=g))
    for _ in range(n_shapes):
        cy, cx, r1, r2, kind = torch.rand(5, generator=g, dtype=torch.float64).tolist()
        r1, r2 = 0.05 + 0.15 * r1, 0.05 + 0.15 * r2
        inside = ((yy - cy) / r1) ** 2 + ((xx - cx) / r2) ** 2 <= 1 if kind < 0.5 else ((yy - cy).abs() <= r1) & ((xx - cx).abs() <= r2)
        colour = torch.rand(3, 1, 1, generator=g, dtype=torch.float64)
        tex = torch.where(inside, colour + 0.1 * (tex - base), tex)
    return _rescale(tex)


def photo_texture(h: int, w: int, seed: int) -> tuple[Tensor, str] | None:
    """(3, H, W) float64 linear texture from a scikit-image sample photo, or None without skimage."""
    try:
        import cv2
        from skimage import data
    except ImportError:
        return None
    name = PHOTOS[int(seed) % len(PHOTOS)]
    try:
        img = getattr(data, name)()
    except Exception:  # noqa: BLE001 - a missing data file falls back to procedural
        return None
    ih, iw = img.shape[:2]
    side = min(ih, iw)
    crop = img[(ih - side) // 2: (ih - side) // 2 + side, (iw - side) // 2: (iw - side) // 2 + side, :3]
    crop = np.ascontiguousarray(crop)
    small = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA).astype(np.float64) / 255.0
    lin = srgb_to_linear(torch.from_numpy(small).permute(2, 0, 1).contiguous())
    lo, hi = TEXTURE_RANGE
    return lo + (hi - lo) * lin, name


def bumpy_normals(h: int, w: int, size: tuple[float, float], g: torch.Generator, max_slope: float = 0.15) -> tuple[Tensor, Tensor]:
    """Smooth seeded height field (H, W) and its unit normals (3, H, W), float64.

    The height is scaled so that the steepest slope is ``max_slope``.
    """
    height = _smooth_noise(g, 1, h, w, 6)[0]
    d_row, d_col = torch.gradient(height, spacing=(size[1] / h, size[0] / w))
    dx, dy = d_col, -d_row  # rows run towards −y
    scale = max_slope / float(torch.sqrt(dx * dx + dy * dy).max().clamp_min(1e-12))
    height, dx, dy = height * scale, dx * scale, dy * scale
    n = torch.stack([-dx, -dy, torch.ones_like(dx)])
    return height, n / torch.linalg.vector_norm(n, dim=0, keepdim=True)


def specular_clusters(
    h: int, w: int, k: int, s: Tensor, alpha: Tensor, g: torch.Generator
) -> tuple[Tensor, Tensor, Tensor]:
    """Voronoi label map (H, W) int64 with K regions and per-cluster s, α (K, 3), float64.

    Cluster 0 keeps (s, α); the others scale s by [0.3, 1.6] and α by e^[−1.2, 1.2].
    """
    sites = torch.rand(k, 2, generator=g, dtype=torch.float64)
    yy = (torch.arange(h, dtype=torch.float64) + 0.5) / h
    xx = (torch.arange(w, dtype=torch.float64) + 0.5) / w
    d = (yy.view(1, -1, 1) - sites[:, 0].view(-1, 1, 1)) ** 2 + (xx.view(1, 1, -1) - sites[:, 1].view(-1, 1, 1)) ** 2
    labels = d.argmin(0)
    f_s = 0.3 + 1.3 * torch.rand(k, 1, generator=g, dtype=torch.float64)
    f_a = torch.exp(2.4 * torch.rand(k, 1, generator=g, dtype=torch.float64) - 1.2)
    f_s[0], f_a[0] = 1.0, 1.0
    return labels, s.view(1, 3) * f_s, alpha.view(1, 3) * f_a


def light_layout(layout: str, shots: int, g: torch.Generator) -> tuple[Tensor, Tensor]:
    """Lights (N, 4) and cameras (N, 4), float64, for one of :data:`LAYOUTS`."""
    n = shots
    cam_xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 0.02
    cam_z = CAMERA_HEIGHT + (torch.rand(n, 1, generator=g, dtype=torch.float64) - 0.5) * 0.02
    cameras = torch.cat([cam_xy, cam_z, torch.ones(n, 1, dtype=torch.float64)], 1)
    phase = float(torch.rand(1, generator=g, dtype=torch.float64)) * 2 * math.pi
    azim = phase + 2 * math.pi * torch.arange(n, dtype=torch.float64) / n
    azim = azim + (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * (math.pi / max(n, 1))
    u = torch.rand(n, generator=g, dtype=torch.float64)
    if layout in ("ring", "hemisphere", "near"):
        if layout == "ring":
            radius, lz = torch.full((n,), 0.025, dtype=torch.float64), torch.full((n,), 0.25, dtype=torch.float64)
        elif layout == "hemisphere":
            radius, lz = 0.035 * torch.sqrt(u), 0.1 + 0.4 * torch.rand(n, generator=g, dtype=torch.float64)
        else:
            radius, lz = 0.025 * torch.sqrt(u), 0.04 + 0.04 * torch.rand(n, generator=g, dtype=torch.float64)
        p = torch.stack([radius * torch.cos(azim), radius * torch.sin(azim)], 1)  # mirror highlight point
        lxy = p + (p - cam_xy) * (lz / cam_z[:, 0]).unsqueeze(1)
        lights = torch.cat([lxy, lz.unsqueeze(1), torch.ones(n, 1, dtype=torch.float64)], 1)
    else:
        lo, hi = (35.0, 88.0) if layout == "far" else (5.0, 15.0)
        elev = torch.deg2rad(lo + (hi - lo) * u)
        d = torch.stack([torch.cos(elev) * torch.cos(azim), torch.cos(elev) * torch.sin(azim), torch.sin(elev)], 1)
        lights = torch.cat([d, torch.zeros(n, 1, dtype=torch.float64)], 1)
    return lights, cameras


def calibrate_intensity(lights: Tensor, mean_texture: float, level: float, g: torch.Generator) -> Tensor:
    """(N, 3) white intensities giving a mean diffuse level ≈ ``level`` over the (flat) sample.

    The geometric factor max(n·l, 0)/d² (point) or max(n·l, 0) (directional) is averaged over a
    16 × 16 grid of the surface, then each shot gets a random factor in [0.85, 1.15].
    """
    pts = surface_points(16, 16, SURFACE, dtype=lights.dtype).reshape(3, -1).T  # (P, 3)
    xyz, w = lights[:, None, :3], lights[:, None, 3:]
    d = xyz - w * pts[None]
    dist2 = (d * d).sum(-1)
    cos = d[..., 2] / dist2.sqrt()
    factor = torch.where(w[..., 0] > 0.5, cos.clamp_min(0) / dist2, cos.clamp_min(0)).mean(1).clamp_min(1e-3)
    jitter = 0.85 + 0.3 * torch.rand(len(lights), generator=g, dtype=torch.float64)
    return (level / (mean_texture * factor) * jitter).unsqueeze(1).expand(-1, 3).contiguous()


def _render(truth: dict, spec: tuple[Tensor, Tensor], normals: Tensor, lights: Tensor, intensities: Tensor,
            cameras: Tensor, size: tuple[float, float]) -> Tensor:
    """Phong (+ sparkle) images shot by shot, (N, 3, H, W) — bounded memory for large sizes."""
    s, alpha = spec
    tex = truth["texture"]
    out = torch.empty((len(lights), 3) + tuple(tex.shape[1:]), dtype=tex.dtype, device=tex.device)
    for k in range(len(lights)):
        sl = slice(k, k + 1)
        img = phong_render(tex, s, alpha, normals, lights[sl], intensities[sl], cameras[sl], size)
        if truth.get("flake_field") is not None:
            img = img + sparkle_render(truth["flake_field"], normals, lights[sl], intensities[sl], cameras[sl], size)
        out[k] = img[0]
    return out


def _check_args(size, shots, texture, alpha, s, layout, noise, bits, exposure, flakes, spec_clusters) -> tuple[int, int]:
    hw = (size, size) if isinstance(size, int) else tuple(size)
    if len(hw) != 2 or not all(isinstance(v, int) and v >= 4 for v in hw):
        raise InputError(f"size: expected an int >= 4 or (height, width), found {size!r}")
    if not isinstance(shots, int) or shots < 1:
        raise InputError(f"shots: expected an int >= 1, found {shots!r}")
    if texture not in TEXTURES:
        raise InputError(f"texture: expected one of {list(TEXTURES)}, found {texture!r}")
    if layout not in LAYOUTS:
        raise InputError(f"layout: expected one of {list(LAYOUTS)}, found {layout!r}")
    for name, v, lo in (("alpha", alpha, 0.0), ("s", s, 0.0)):
        if len(v) != 3 or not all(math.isfinite(x) and x >= lo for x in v):
            raise InputError(f"{name}: expected 3 finite values >= {lo}, found {tuple(v)!r}")
    if not (math.isfinite(noise) and noise >= 0):
        raise InputError(f"noise: expected a relative std >= 0, found {noise!r}")
    if bits not in (None, 8, 16):
        raise InputError(f"bits: expected None, 8 or 16, found {bits!r}")
    if not (math.isfinite(exposure) and exposure > 0):
        raise InputError(f"exposure: expected a positive number, found {exposure!r}")
    if flakes is not None and not isinstance(flakes, FlakeModel):
        raise InputError(f"flakes: expected a FlakeModel or None, found {type(flakes).__name__}")
    if not isinstance(spec_clusters, int) or spec_clusters < 1:
        raise InputError(f"spec_clusters: expected an int >= 1, found {spec_clusters!r}")
    return hw  # type: ignore[return-value]


def synth_capture(
    *, size: int | tuple[int, int] = 256, shots: int = 12, seed: int = 0, texture: str = "auto",
    alpha: tuple[float, float, float] = (40.0, 60.0, 80.0), s: tuple[float, float, float] = (0.6, 0.6, 0.6),
    layout: str = "ring", bumpy: bool = False, noise: float = 0.0, bits: int | None = None, exposure: float = 1.0,
    flakes: FlakeModel | None = None, spec_clusters: int = 1, dtype: torch.dtype = torch.float32,
) -> SynthResult:
    """Render a synthetic capture with known truth.

    Args:
        size: image size, int (square) or (height, width).
        shots: number of shots N.
        seed: seeds every random choice (texture, normals, clusters, lights, noise).
        texture: "procedural" (seeded colour noise + shapes), "photo" (a scikit-image sample
            photo, linearised; falls back to procedural without scikit-image) or "auto" (photo
            when available). Values lie in [0.05, 0.7].
        alpha, s: per-channel Phong exponent and strength (cluster 0 when clustered).
        layout: one of :data:`LAYOUTS`.
        bumpy: smooth seeded height field → normals (max slope 0.15) instead of flat.
        noise: Gaussian noise std relative to each image's mean.
        bits: None (float images, only clamped at 0) or 8/16: clip to [0, 1] and quantise as
            the file would; ``saturated`` marks values at the encoding maximum.
        exposure: scales every light intensity.
        flakes: add the sparkle of this flake model's deterministic field.
        spec_clusters: K ≥ 2 gives a spatially varying specular truth (K Voronoi regions).
        dtype: floating dtype of every tensor (CPU).

    Returns:
        :class:`SynthResult` (capture, truth, params).
    """
    h, w = _check_args(size, shots, texture, alpha, s, layout, noise, bits, exposure, flakes, spec_clusters)
    tex64, texture_name = _pick_texture(texture, h, w, seed)
    truth = _synth_truth(tex64, h, w, s, alpha, bumpy=bumpy, spec_clusters=spec_clusters, flakes=flakes, seed=seed,
                         dtype=dtype)
    normals = truth["normals"]
    lights, cameras, intensities = _synth_lights(layout, shots, seed, float(tex64.mean()), exposure, dtype)
    result = SynthResult(capture=None, truth=truth)  # type: ignore[arg-type]
    images, saturated = _synth_images(result, lights, intensities, cameras, noise=noise, bits=bits, seed=seed,
                                      dtype=dtype)
    result.capture = Capture(
        images=images, normals=None if not bumpy else normals, lights=lights, intensities=intensities,
        cameras=cameras, size=SURFACE, saturated=saturated, names=[f"images/{k:03d}.png" for k in range(shots)],
        color_space="linear",
    )
    result.params = {
        "size": [h, w], "shots": shots, "seed": int(seed), "texture": texture_name, "alpha": list(map(float, alpha)),
        "s": list(map(float, s)), "layout": layout, "bumpy": bool(bumpy), "noise": float(noise), "bits": bits,
        "exposure": float(exposure), "flakes": flakes.to_dict() if flakes is not None else None,
        "spec_clusters": spec_clusters, "dtype": str(dtype).removeprefix("torch."),
    }
    return result


def _pick_texture(texture: str, h: int, w: int, seed: int) -> tuple[Tensor, str]:
    """(texture (3, H, W) float64, its name): a photo for "auto"/"photo" when one is available, else procedural."""
    texture_name = "procedural"
    tex64 = None
    if texture in ("auto", "photo"):
        photo = photo_texture(h, w, seed)
        if photo is not None:
            tex64, name = photo
            texture_name = f"photo:{name}"
    if tex64 is None:
        tex64 = procedural_texture(h, w, _generator(seed, _TEXTURE))
    return tex64, texture_name


def _synth_truth(tex64: Tensor, h: int, w: int, s: tuple[float, float, float], alpha: tuple[float, float, float], *,
                 bumpy: bool, spec_clusters: int, flakes: FlakeModel | None, seed: int, dtype: torch.dtype) -> dict:
    """The truth (:class:`SynthResult`'s keys) of texture ``tex64``: normals, specular (clusters), flakes."""
    s64 = torch.tensor(s, dtype=torch.float64)
    a64 = torch.tensor(alpha, dtype=torch.float64)
    truth: dict = {"texture": tex64.to(dtype), "s": s64.to(dtype), "alpha": a64.to(dtype)}
    height_field = None
    if bumpy:
        height_field, n64 = bumpy_normals(h, w, SURFACE, _generator(seed, _NORMALS))
        normals = n64.to(dtype)
    else:
        normals = torch.zeros(3, h, w, dtype=dtype)
        normals[2] = 1.0
    truth["normals"] = normals
    truth["height_field"] = None if height_field is None else height_field.to(dtype)
    if spec_clusters >= 2:
        labels, cs, ca = specular_clusters(h, w, spec_clusters, s64, a64, _generator(seed, _CLUSTERS))
        area = torch.bincount(labels.reshape(-1), minlength=spec_clusters).to(torch.float64) / labels.numel()
        truth.update(spec_labels=labels, cluster_s=cs.to(dtype), cluster_alpha=ca.to(dtype),
                     s=(area @ cs).to(dtype), alpha=(area @ ca).to(dtype))
    truth["flakes"] = flakes
    truth["flake_field"] = flake_field(flakes, h, w, normals) if flakes is not None else None
    return truth


def _synth_lights(layout: str, shots: int, seed: int, mean_texture: float, exposure: float,
                  dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor]:
    """(lights (N, 4), cameras (N, 4), intensities (N, 3)) of the layout, intensities calibrated to the texture."""
    g_geo = _generator(seed, _GEOMETRY)
    lights64, cameras64 = light_layout(layout, shots, g_geo)
    inten64 = calibrate_intensity(lights64, mean_texture, DIFFUSE_LEVEL * exposure, g_geo)
    return lights64.to(dtype), cameras64.to(dtype), inten64.to(dtype)


def _synth_images(result: SynthResult, lights: Tensor, intensities: Tensor, cameras: Tensor, *, noise: float,
                  bits: int | None, seed: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """(images (N, 3, H, W), saturated (N, 3, H, W) bool): the truth rendered, noise added, clamped at 0 and, with
    ``bits``, clipped to [0, 1] and quantised as the file would be."""
    truth = result.truth
    images = _render(truth, result.specular_maps(), truth["normals"], lights, intensities, cameras, SURFACE)
    if noise > 0:
        g_noise = _generator(seed, _NOISE)
        for k in range(len(lights)):
            sigma = noise * float(images[k].mean())
            images[k] += sigma * torch.randn(images[k].shape, generator=g_noise, dtype=dtype)
    images.clamp_(min=0.0)
    if bits is not None:
        top = PNG_MAX[bits]
        q = torch.round(images.double().clamp(0.0, 1.0) * top)
        saturated = q == top
        images = q.to(dtype) / top  # the same float a reader gets from the file
    else:
        saturated = torch.zeros(images.shape, dtype=torch.bool)
    return images, saturated


# ---------------------------------------------------------------------------------- on disk


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def _hwc(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().float().permute(1, 2, 0).numpy())


def write_synth(result: SynthResult, out_dir: str | os.PathLike, *, bits: int | str | None = None) -> Path:
    """Save the capture in ``out_dir`` and its truth in ``out_dir/truth/``, atomically.

    Args:
        bits: image encoding for :func:`~torchmetal.io.capture_save.save_capture` semantics
            (8, 16 or "npy"); default: the bit depth the capture was quantised to, else "npy"
            — either way the capture re-loads bit-exactly.

    ``truth/``: truth.json (format "torchmetal-synth-truth": s, alpha, cluster s/α, flake
    model dict, params), texture.npy (H, W, 3) float32, clean.npy (N, H, W, 3) float32 — the
    noise-free, unclipped linear render of every shot (score any held-out shot against it, not
    against its noisy photo), spec_labels.npy (H, W) int32 when clustered, height.npy (H, W) when
    bumpy (the normals are the capture's normals.npy).
    """
    if bits is None:
        bits = result.params.get("bits") or "npy"
    path, tmp = prepare_target(out_dir)
    try:
        write_capture_files(result.capture, tmp, bits=bits)
        t = result.truth
        tdir = tmp / "truth"
        tdir.mkdir()
        meta = {
            "format": TRUTH_FORMAT, "version": 1,
            "surface": {"width": result.capture.size[0], "height": result.capture.size[1]},
            "texture": "texture.npy", "s": t["s"].double().tolist(), "alpha": t["alpha"].double().tolist(),
            "clusters": None, "height_field": None,
            "normals": "../normals.npy" if not result.capture.flat else None,
            "flakes": t["flakes"].to_dict() if t["flakes"] is not None else None,
            "params": result.params,
        }
        (tdir / "texture.npy").write_bytes(_npy_bytes(_hwc(t["texture"])))
        clean = result.render_clean().detach().cpu().float().permute(0, 2, 3, 1).numpy()
        (tdir / "clean.npy").write_bytes(_npy_bytes(np.ascontiguousarray(clean)))
        meta["clean"] = "clean.npy"
        if t.get("spec_labels") is not None:
            (tdir / "spec_labels.npy").write_bytes(_npy_bytes(t["spec_labels"].cpu().numpy().astype(np.int32)))
            meta["clusters"] = {"labels": "spec_labels.npy", "s": t["cluster_s"].double().tolist(),
                                "alpha": t["cluster_alpha"].double().tolist()}
        if t.get("height_field") is not None:
            (tdir / "height.npy").write_bytes(_npy_bytes(t["height_field"].cpu().float().numpy()))
            meta["height_field"] = "height.npy"
        atomic_write_bytes(tdir / "truth.json", (json.dumps(meta, indent=1, allow_nan=False) + "\n").encode())
        replace_dir(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def read_synth_truth(path: str | os.PathLike) -> dict:
    """Read ``truth/`` written by :func:`write_synth` (path: the capture dir or its truth dir).

    Returns a dict with texture (3, H, W) float32, s, alpha (3,), flakes (FlakeModel or None),
    params, clean (N, 3, H, W) float32 noise-free renders of the shots (when written), and
    spec_labels (H, W) int64 / cluster_s / cluster_alpha (K, 3) when clustered.
    """
    root = Path(path)
    tdir = root if (root / "truth.json").is_file() else root / "truth"
    f = tdir / "truth.json"
    if not f.is_file():
        raise CaptureError(f"{f}: expected a synthetic-truth description, found nothing")
    try:
        meta = json.loads(f.read_text())
    except json.JSONDecodeError as e:
        raise CaptureError(f"{f}: expected valid JSON, found a syntax error at line {e.lineno} column {e.colno} ({e.msg})") from None
    if not isinstance(meta, dict) or meta.get("format") != TRUTH_FORMAT:
        raise CaptureError(f"{f}: expected format {TRUTH_FORMAT!r}, found {meta.get('format') if isinstance(meta, dict) else meta!r}")
    tex = np.load(tdir / meta["texture"], allow_pickle=False)
    out = {
        "texture": torch.from_numpy(tex).permute(2, 0, 1).contiguous(),
        "s": torch.tensor(meta["s"], dtype=torch.float32), "alpha": torch.tensor(meta["alpha"], dtype=torch.float32),
        "flakes": FlakeModel.from_dict(meta["flakes"]) if meta.get("flakes") else None, "params": meta.get("params", {}),
    }
    if meta.get("clean"):
        out["clean"] = torch.from_numpy(np.load(tdir / meta["clean"], allow_pickle=False)).permute(0, 3, 1, 2).contiguous()
    if meta.get("clusters"):
        cl = meta["clusters"]
        out["spec_labels"] = torch.from_numpy(np.load(tdir / cl["labels"], allow_pickle=False).astype(np.int64))
        out["cluster_s"] = torch.tensor(cl["s"], dtype=torch.float32)
        out["cluster_alpha"] = torch.tensor(cl["alpha"], dtype=torch.float32)
    if meta.get("height_field"):
        out["height_field"] = torch.from_numpy(np.load(tdir / meta["height_field"], allow_pickle=False))
    return out
