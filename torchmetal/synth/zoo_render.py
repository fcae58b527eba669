"""The scene zoo's generator: captures from code independent of the fit's own model code.

The scenes themselves are listed in :mod:`torchmetal.synth.zoo`.

Everything here is numpy (no torchmetal geometry, Phong or flake field), so a bug shared by the
fit and its own synthetic generator cannot hide. A :class:`Scene` says what the capture is like;
:func:`make_case` renders it deterministically from its seed and writes a docs/design.md §2.1 capture
directory (the files a user would bring: 8-bit sRGB or 16-bit linear PNGs, or float NPY), plus
held-out shots kept *outside* the capture with their noise-free, unclipped linear renders.

Truth lobes: ``phong`` (docs/design.md §2.2), ``blinn`` (s·(n·h)^{4α}, about the same width) and ``ggx``
(Trowbridge–Reitz D(n·h) with a² = 2/(α+2), normalised to peak s). Flakes are elliptical discs
(Poisson positions, log-normal area, uniform orientation) with Rayleigh-distributed tilt about the
surface normal under each flake and a
Gaussian glint in the angle between the flake normal and the half vector, added on top of the
coating — unlike the project's hash field. Noise is signal-dependent: σ = noise·√I + 0.1·noise.

:func:`oracle_render` gives the reach of the truth's own specular terms: the texture solved by
least squares from the (noisy, clipped) fit shots with the true specular and flakes known, then
rendered for the held-out shots. No fit of d(p) from these shots can do much better.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from torchmetal.synth.zoo_flakes import flake_cover, flake_glints, flake_normals, flake_pixels, make_flakes
from torchmetal.synth.zoo_shading import WIDTH, lobe_value, sph, surface_points, towards, unit

__all__ = ["Scene", "ZooCase", "make_case", "render_clean", "oracle_render", "decode"]

CAMERA_HEIGHT = 0.3
TEX_RANGE = (0.05, 0.7)
DIFFUSE_LEVEL = 0.25
LAYOUTS = ("hemisphere", "ring", "few", "directional", "grazing", "dome", "blind")
CAMERAS = ("fixed", "jitter", "ortho")
LOBES = ("phong", "blinn", "ggx", "ggx_full")  # ggx: the normal distribution D/D(0) alone; ggx_full: torchmetal's
#: microfacet lobe (D̂·F̂·G₁(n·l)·G₁(n·v)/(n·v), :func:`torchmetal.lobes.ggx_lobe`), written again here in numpy
ENCODINGS = ("srgb8", "linear16", "float")


@dataclass(frozen=True)
class Scene:
    """What one zoo capture is like (all lengths in metres, angles in degrees).

    ``flakes`` (or None): density (flakes/px), area_median (px²), area_log_std, aspect (range of
    minor/major), tilt_sigma (Rayleigh σ of the tilt, radians), glint_sigma (radians), color (3,),
    optional region ("left": flakes only where x < 0, density counted there).
    ``second``: (s, α) of a foil disc of radius 0.3·width in the centre (darker texture there).
    """

    name: str
    size: int = 192
    shots: int = 12
    held: int = 3
    layout: str = "hemisphere"
    camera: str = "jitter"
    texture: str = "procedural"  # procedural | highfreq | photo:<skimage name>
    normals: str = "flat"  # flat | bumpy | sphere (a spherical cap: 60° tilt at the corners)
    lobe: str = "phong"
    tint: tuple[float, float, float] | None = None  # per-channel mean of the texture (None: as drawn)
    s: float = 0.5
    alpha: float = 60.0
    second: tuple[float, float] | None = None
    flakes: dict | None = None
    encoding: str = "srgb8"
    noise: float = 0.01
    exposure: float = 1.0
    seed: int = 0

    def __post_init__(self) -> None:
        for name, value, options in (("layout", self.layout, LAYOUTS), ("camera", self.camera, CAMERAS),
                                     ("lobe", self.lobe, LOBES), ("encoding", self.encoding, ENCODINGS)):
            if value not in options:
                raise ValueError(f"Scene.{name}: expected one of {options}, found {value!r}")

    @property
    def phong_truth(self) -> bool:
        """True when docs/design.md §2.2's model (global Phong, no flakes) is exactly the truth."""
        return self.lobe == "phong" and self.second is None and self.flakes is None

    def with_(self, **kw) -> "Scene":
        return replace(self, **kw)


# ---------------------------------------------------------------------------- ingredients


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, stream])


def _smooth(rng: np.random.Generator, c: int, h: int, w: int, cells: int) -> np.ndarray:
    """(c, h, w) smooth noise in about [0, 1]: bicubic upsampling of a coarse random grid."""
    import cv2

    g = rng.random((cells + 3, cells + 3, c)).astype(np.float32)
    big = cv2.resize(g, (w + 3 * w // cells, h + 3 * h // cells), interpolation=cv2.INTER_CUBIC)
    y0, x0 = h // cells, w // cells
    out = big[y0:y0 + h, x0:x0 + w].reshape(h, w, c)
    return np.clip(out, 0.0, 1.0).transpose(2, 0, 1).astype(np.float64)


def _rescale(t: np.ndarray) -> np.ndarray:
    lo, hi = float(t.min()), float(t.max())
    return TEX_RANGE[0] + (t - lo) / max(hi - lo, 1e-12) * (TEX_RANGE[1] - TEX_RANGE[0])


def srgb_decode(x: np.ndarray) -> np.ndarray:
    """sRGB code values in [0, 1] → linear (the IEC 61966-2-1 curve)."""
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """Linear [0, 1] → sRGB code values in [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def make_texture(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """(3, n, n) linear diffuse texture in TEX_RANGE."""
    import cv2

    if kind.startswith("photo:"):
        from skimage import data

        img = getattr(data, kind.split(":", 1)[1])()[..., :3]
        side = min(img.shape[:2])
        img = img[:side, :side]
        img = cv2.resize(img, (n, n), interpolation=cv2.INTER_AREA).astype(np.float64) / 255.0
        return _rescale(srgb_decode(img).transpose(2, 0, 1))
    if kind == "highfreq":  # 1–3 px stripes and checks, plus fine noise: looks like glitter to a careless detector
        yy, xx = np.mgrid[0:n, 0:n]
        checks = ((yy // 2 + xx // 2) % 2).astype(np.float64)
        stripes = 0.5 + 0.5 * np.sin(2 * math.pi * xx / 3.0 + 0.7 * yy)
        base = _smooth(rng, 3, n, n, 6)
        t = 0.45 * base + 0.3 * checks[None] * np.array([1.0, 0.6, 0.3])[:, None, None] + 0.25 * stripes[None]
        t = t + 0.15 * rng.random((3, n, n))
        return _rescale(t)
    if kind == "procedural":
        t = 0.6 * _smooth(rng, 3, n, n, 5) + 0.4 * _smooth(rng, 3, n, n, 24)
        return _rescale(t)
    raise ValueError(f"texture: expected procedural, highfreq or photo:<name>, found {kind!r}")


def make_normals(kind: str, n: int, rng: np.random.Generator, max_slope: float = 0.2) -> np.ndarray:
    """(3, n, n) unit normals: flat, or a smooth random height field's."""
    if kind == "flat":
        out = np.zeros((3, n, n))
        out[2] = 1.0
        return out
    if kind == "sphere":  # the cap of a sphere whose slope reaches 60° at the corners (curved, like a ball)
        p = surface_points(n)
        radius = math.sqrt(2.0) * 0.5 * WIDTH / math.sin(math.radians(60.0))
        z = np.sqrt(np.clip(radius**2 - p[0] ** 2 - p[1] ** 2, 0.0, None))
        return unit(np.stack([p[0], p[1], z]))
    if kind != "bumpy":
        raise ValueError(f"normals: expected flat, bumpy or sphere, found {kind!r}")
    h = _smooth(rng, 1, n, n, 10)[0] + 0.5 * _smooth(rng, 1, n, n, 20)[0]
    gy, gx = np.gradient(h)
    scale = max_slope / max(float(np.abs(np.stack([gx, gy])).max()), 1e-12)
    gx, gy = gx * scale, gy * scale
    nn = np.stack([-gx, gy, np.ones_like(gx)])  # row index runs towards −y
    return nn / np.linalg.norm(nn, axis=0, keepdims=True)


def make_layout(scene: Scene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lights (K, 4), cameras (K, 4) and a per-shot exposure factor (K,), fit shots first."""
    k = scene.shots + scene.held
    lights, cams = np.zeros((k, 4)), np.zeros((k, 4))
    for i in range(k):
        if scene.camera == "ortho":
            cams[i] = [*sph(85.0 + rng.uniform(-2, 2), rng.uniform(0, 360)), 0.0]
        else:
            jit = rng.uniform(-0.05, 0.05, 2) if scene.camera == "jitter" else np.zeros(2)
            cams[i] = [jit[0], jit[1], CAMERA_HEIGHT, 1.0]
        cam_xy = cams[i, :2] if cams[i, 3] == 1 else np.zeros(2)
        lay = scene.layout
        if lay == "hemisphere":
            d = rng.uniform(0.25, 0.4)
            lights[i] = [*(d * sph(rng.uniform(25, 80), rng.uniform(0, 360))), 1.0]
        elif lay == "ring":  # mirror point on a ring of radius 0.025 around the centre
            hl = 0.25
            ang = 2 * math.pi * i / k + rng.uniform(-0.2, 0.2)
            m = 0.025 * np.array([math.cos(ang), math.sin(ang)])
            lxy = m + (m - cam_xy) * hl / CAMERA_HEIGHT
            lights[i] = [lxy[0], lxy[1], hl, 1.0]
        elif lay == "few":  # 3 fit shots (and the held-out ones) put their mirror point on the sample
            seen = i < 3 or i >= scene.shots
            if seen:
                m = rng.uniform(-0.03, 0.03, 2)
                hl = rng.uniform(0.2, 0.35)
                lxy = m + (m - cam_xy) * hl / CAMERA_HEIGHT
                lights[i] = [lxy[0], lxy[1], hl, 1.0]
            else:
                lights[i] = [*(0.3 * sph(rng.uniform(20, 35), rng.uniform(0, 360))), 1.0]
        elif lay == "directional":
            lights[i] = [*sph(rng.uniform(3, 89), rng.uniform(0, 360)), 0.0]
            if i % 3 == 0:  # a third of the shots near the camera's mirror direction
                c = cams[i, :3] if cams[i, 3] == 0 else unit(cams[i, :3:1].reshape(3, 1))[:, 0]
                mirror = np.array([-c[0], -c[1], c[2]])
                lights[i, :3] = unit((mirror + rng.normal(0, 0.05, 3)).reshape(3, 1))[:, 0]
                lights[i, 2] = abs(lights[i, 2])
        elif lay == "grazing":
            lights[i] = [*sph(rng.uniform(5, 15), rng.uniform(0, 360)), 0.0]
        elif lay == "dome":  # rings of directional lights over the hemisphere
            ring, pos = divmod(i, 12)
            elev = 15 + 70 * (ring + 0.5) / max(1, math.ceil(k / 12))
            lights[i] = [*sph(elev + rng.uniform(-3, 3), 30 * pos + 15 * ring + rng.uniform(-5, 5)), 0.0]
        elif lay == "blind":  # fit shots never near the mirror direction; held-out shots closer to it
            if i < scene.shots:
                lights[i] = [*(0.3 * sph(rng.uniform(20, 40), rng.uniform(0, 360))), 1.0]
            else:
                lights[i] = [*(0.3 * sph(rng.uniform(45, 55), rng.uniform(0, 360))), 1.0]
    factor = rng.uniform(0.85, 1.15, k)
    return lights, cams, factor


# ---------------------------------------------------------------------------- rendering


@dataclass
class Truth:
    """The parameters behind a zoo capture (numpy, channel-first)."""

    texture: np.ndarray  # (3, n, n)
    normals: np.ndarray  # (3, n, n)
    s: np.ndarray  # (3, n, n) spatial (two materials) — global scenes are constant
    alpha: np.ndarray  # (3, n, n)
    lobe: str
    flakes: dict | None = None
    cover: list | None = None


def render_clean(truth: Truth, light: np.ndarray, intensity: np.ndarray, camera: np.ndarray,
                 *, specular: bool = True, flakes: bool = True) -> np.ndarray:
    """(3, n, n) noise-free, unclipped linear radiance of one shot."""
    n = truth.texture.shape[-1]
    p = surface_points(n)
    l, d2 = towards(p, light)
    v, _ = towards(p, camera)
    e = intensity.reshape(3, 1, 1) / (d2[None] if light[3] == 1 else 1.0)
    nn = truth.normals
    nl = (nn * l).sum(0)[None]
    img = e * truth.texture * np.clip(nl, 0.0, None)
    if specular:
        img = img + e * lobe_value(truth.lobe, nn, l, v, truth.s, truth.alpha)
    if flakes and truth.flakes is not None:
        img = img + flake_glints(truth, l, v, e)
    return img


# ---------------------------------------------------------------------------- a case


@dataclass
class ZooCase:
    """A written zoo capture and what scores it.

    ``capture_dir`` holds only the fit shots. Held-out shots: ``held_lights`` (H, 4),
    ``held_intensities`` (H, 3), ``held_cameras`` (H, 4) and ``clean`` (H, 3, n, n) float32,
    their noise-free unclipped linear renders. ``truth_stats``: s, α (3,), flake statistics.
    """

    scene: Scene
    capture_dir: Path
    truth: Truth
    held_lights: np.ndarray
    held_intensities: np.ndarray
    held_cameras: np.ndarray
    clean: np.ndarray
    fit_lights: np.ndarray
    fit_intensities: np.ndarray
    fit_cameras: np.ndarray
    truth_stats: dict = field(default_factory=dict)
    flake_pixels: np.ndarray | None = None  # (n, n) bool: pixels a true flake covers, grown by 1 px


def _intensity(light: np.ndarray, tex_mean: float, exposure: float, factor: float) -> np.ndarray:
    """Intensity putting the mean diffuse level at the centre at DIFFUSE_LEVEL·exposure (n·l floored at 0.3)."""
    if light[3] == 1:
        d2 = float((light[:3] ** 2).sum())
        nl = light[2] / math.sqrt(d2)
    else:
        d2, nl = 1.0, light[2] / float(np.linalg.norm(light[:3]))
    e = DIFFUSE_LEVEL * exposure * factor / (tex_mean * max(nl, 0.3))
    return np.full(3, e * d2)


def _encode(img: np.ndarray, scene: Scene, rng: np.random.Generator) -> np.ndarray:
    """(3, n, n) linear → stored (n, n, 3) array: noisy, clipped and quantised as the encoding says."""
    noisy = img + scene.noise * (np.sqrt(np.clip(img, 0, None)) + 0.1) * rng.normal(size=img.shape)
    hwc = noisy.transpose(1, 2, 0)
    if scene.encoding == "srgb8":
        return np.round(srgb_encode(hwc) * 255.0).astype(np.uint8)
    if scene.encoding == "linear16":
        return np.round(np.clip(hwc, 0.0, 1.0) * 65535.0).astype(np.uint16)
    return np.clip(hwc, 0.0, None).astype(np.float32)


def decode(stored: np.ndarray, encoding: str) -> tuple[np.ndarray, np.ndarray]:
    """Stored (n, n, 3) → linear (3, n, n) and saturated (3, n, n) bool (the oracle's own decoder)."""
    if encoding == "srgb8":
        return srgb_decode(stored.astype(np.float64) / 255.0).transpose(2, 0, 1), (stored == 255).transpose(2, 0, 1)
    if encoding == "linear16":
        return (stored.astype(np.float64) / 65535.0).transpose(2, 0, 1), (stored == 65535).transpose(2, 0, 1)
    return stored.astype(np.float64).transpose(2, 0, 1), np.zeros(stored.shape[::-1][:1] + stored.shape[:2], bool)


def make_truth(scene: Scene) -> Truth:
    n = scene.size
    tex = make_texture(scene.texture, n, _rng(scene.seed, 0))
    if scene.tint is not None:  # each channel scaled to the tint's mean albedo
        tex = tex * (np.asarray(scene.tint, dtype=np.float64) / tex.mean((1, 2)))[:, None, None]
    normals = make_normals(scene.normals, n, _rng(scene.seed, 1))
    s = np.full((3, n, n), scene.s)
    alpha = np.full((3, n, n), scene.alpha)
    if scene.second is not None:
        p = surface_points(n)
        disc = (p[0] ** 2 + p[1] ** 2) < (0.3 * WIDTH) ** 2
        s[:, disc], alpha[:, disc] = scene.second[0], scene.second[1]
        tex = np.where(disc[None], 0.3 * tex, tex)
    truth = Truth(texture=tex, normals=normals, s=s, alpha=alpha, lobe=scene.lobe)
    if scene.flakes is not None:
        truth = with_drawn_flakes(truth, scene.flakes, _rng(scene.seed, 2))
    return truth


def with_drawn_flakes(truth: Truth, spec: dict, rng: np.random.Generator) -> Truth:
    """``truth`` with flakes drawn from ``spec`` (:func:`~torchmetal.synth.zoo_flakes.make_flakes`) by ``rng``: their
    discs, the pixels they cover and their world normals ((3, F), fixed: computed once, not per shot)."""
    n = truth.texture.shape[-1]
    fl = make_flakes(spec, n, rng)
    fl["spec"] = dict(spec)
    drawn = replace(truth, flakes=fl, cover=flake_cover(fl, n))
    fl["world_normal"] = flake_normals(drawn)
    return drawn


def write_capture_dir(out: Path, truth: Truth, shots: int, lights: np.ndarray, ints: np.ndarray, cams: np.ndarray, *,
                      encoding: str, encode, normals: bool, capture_lights: np.ndarray | None = None) -> None:
    """Write the first ``shots`` shots of a rendered scene as a capture directory under ``out``: each clean render
    of ``truth`` passed through ``encode`` ((3, n, n) linear → stored (n, n, 3), in shot order: it may draw noise)
    and written as ``encoding`` says, capture.json with ``capture_lights`` (default ``lights``: a capture's lights
    may differ from the ones that rendered it), and the true normals.npy where ``normals``."""
    import cv2  # on use: OpenCV only where a capture is written

    told = lights if capture_lights is None else capture_lights
    records = []
    for i in range(shots):
        stored = encode(render_clean(truth, lights[i], ints[i], cams[i]))
        if encoding == "float":
            name = f"images/{i:03d}.npy"
            np.save(out / name, stored)
        else:
            name = f"images/{i:03d}.png"
            cv2.imwrite(str(out / name), np.ascontiguousarray(stored[..., ::-1]))
        records.append({"image": name, "light": told[i].tolist(), "light_intensity": ints[i].tolist(),
                        "camera": cams[i].tolist()})
    meta = {"format": "torchmetal-capture", "version": 1, "color_space": "srgb" if encoding == "srgb8" else "linear",
            "surface": {"width": WIDTH, "height": WIDTH}, "shots": records}
    if normals:
        np.save(out / "normals.npy", truth.normals.transpose(1, 2, 0).astype(np.float32))
        meta["normals"] = "normals.npy"
    (out / "capture.json").write_text(json.dumps(meta, indent=1))


def make_case(scene: Scene, out_dir: str | os.PathLike) -> ZooCase:
    """Render ``scene`` and write its capture directory under ``out_dir`` (created)."""
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    truth = make_truth(scene)
    lights, cams, factor = make_layout(scene, _rng(scene.seed, 3))
    tex_mean = float(truth.texture.mean())
    ints = np.stack([_intensity(lights[i], tex_mean, scene.exposure, factor[i]) for i in range(len(lights))])
    noise_rng = _rng(scene.seed, 4)
    write_capture_dir(out, truth, scene.shots, lights, ints, cams, encoding=scene.encoding,
                      encode=lambda img: _encode(img, scene, noise_rng), normals=scene.normals != "flat")
    held = slice(scene.shots, scene.shots + scene.held)
    clean = np.stack([render_clean(truth, lights[i], ints[i], cams[i]) for i in range(scene.shots, len(lights))])
    stats = {"s": float(scene.s), "alpha": float(scene.alpha)}
    if truth.flakes is not None:
        fl = truth.flakes
        stats.update(density=len(fl["area"]) / scene.size ** 2, median_area=float(np.median(fl["area"])),
                     tilt_sigma=float(scene.flakes["tilt_sigma"]), color=float(np.mean(fl["color"])))
    return ZooCase(scene=scene, capture_dir=out, truth=truth, held_lights=lights[held], held_intensities=ints[held],
                   held_cameras=cams[held], clean=clean.astype(np.float32), fit_lights=lights[:scene.shots],
                   fit_intensities=ints[:scene.shots], fit_cameras=cams[:scene.shots], truth_stats=stats,
                   flake_pixels=flake_pixels(truth))


def oracle_render(case: ZooCase) -> np.ndarray:
    """(H, 3, n, n) held-out renders with the true specular and flakes and the texture solved from the fit shots."""
    import cv2

    truth, scene = case.truth, case.scene
    meta = json.loads((case.capture_dir / "capture.json").read_text())
    num = np.zeros_like(truth.texture)
    den = np.zeros_like(truth.texture)
    for i, shot in enumerate(meta["shots"]):
        f = case.capture_dir / shot["image"]
        stored = np.load(f) if f.suffix == ".npy" else cv2.imread(str(f), cv2.IMREAD_UNCHANGED)[..., ::-1]
        y, sat = decode(stored, scene.encoding)
        lit = Truth(texture=np.ones_like(truth.texture), normals=truth.normals, s=truth.s, alpha=truth.alpha,
                    lobe=truth.lobe, flakes=truth.flakes, cover=truth.cover)
        full = render_clean(lit, case.fit_lights[i], case.fit_intensities[i], case.fit_cameras[i])
        diffuse = render_clean(lit, case.fit_lights[i], case.fit_intensities[i], case.fit_cameras[i],
                               specular=False, flakes=False)
        other = full - diffuse  # specular + flakes
        ok = ~sat
        num += np.where(ok, diffuse * (y - other), 0.0)
        den += np.where(ok, diffuse * diffuse, 0.0)
    tex = np.where(den > 0, num / np.where(den > 0, den, 1.0), truth.texture)
    return held_out_renders(case, replace(truth, texture=np.clip(tex, 0.0, None)))


def held_out_renders(case: ZooCase, truth: Truth | None = None, *, flakes: bool = True) -> np.ndarray:
    """(H, 3, n, n) float32 noise-free renders of ``case``'s held-out shots: of ``truth`` (default the case's own),
    with or without its flakes."""
    truth = case.truth if truth is None else truth
    return np.stack([render_clean(truth, lt, e, c, flakes=flakes)
                     for lt, e, c in zip(case.held_lights, case.held_intensities, case.held_cameras)]).astype(np.float32)


def redrawn_flakes_render(case: ZooCase, draw: int) -> np.ndarray:
    """(H, 3, n, n) held-out renders of the truth with its flakes drawn again from the same statistics.

    What a perfect statistical flake model renders: the true coating and flake statistics, the flakes at
    other places (draw ``draw``, a stream apart from the capture's own). Its PSNR against the clean
    held-out shots is what sparkles at random places can reach; ``case.truth`` without flakes
    scores higher, so the coat alone is no yardstick for a render with sparkles.
    """
    scene = case.scene
    if scene.flakes is None:
        raise ValueError(f"redrawn_flakes_render: scene {scene.name!r} has no flakes")
    return held_out_renders(case, with_drawn_flakes(case.truth, scene.flakes, _rng(scene.seed, 100 + draw)))
