"""Randomized captures for calibrating the fit's automatic choices on a distribution (issue 41, item 3).

:func:`random_scene` draws, from a seed, what real captures vary: 1–3 materials (Voronoi regions of their own
s, α and texture level), a Phong / Blinn / GGX-with-Fresnel-and-shadowing truth lobe, white or coloured
(metal) specular, smooth gloss maps or none, a flat, bumpy or embossed surface (its normals.npy given or
not), a flash beside the lens / a dome of point lights / directional lights, light positions in capture.json
exact or off (the flash's one move of every light, or per-shot jitter), 8-bit sRGB / 16-bit / float
encodings, shot + read noise, clipping (an honest per-channel clip, or a phone's processed one that
whitens the whole pixel), flakes or none (uniform or on one half). :func:`make_random_case` renders it
with the zoo's numpy generator (:mod:`torchmetal.synth.zoo_render`: no torchmetal geometry, lobe or flake
code) into a capture directory plus noise-free held-out shots (a :class:`~torchmetal.synth.zoo_render.ZooCase`),
and :func:`scene_truth` says, per choice name as the fit's ``Decision`` records spell it, whether the truth
is the reference ("reference"), the extension ("extension") or neither ("n/a").

Seeds: the zoo's scenes use seeds 0–18; these draw from ``numpy.random.default_rng([SEED_BASE, seed])`` and
render with scene seeds ``SEED_BASE + seed``, so the two never share a stream.

Sizes are small (32²–40², 48² with flakes, denser than the zoo's so that enough of them glint; 6–9 fit
shots + 3 held out) so that one scene's dozen fits take seconds: the default's light test alone took 12 s of
a 56² × 7 scene's 14 s fit (2026-12-06, one thread), 6 s at 32².
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from torchmetal.synth.zoo_flakes import flake_normals, flake_pixels
from torchmetal.synth.zoo_render import (
    CAMERA_HEIGHT,
    Scene,
    Truth,
    ZooCase,
    _intensity,
    _rng,
    _smooth,
    make_layout,
    make_normals,
    make_truth,
    render_clean,
    srgb_encode,
    write_capture_dir,
)
from torchmetal.synth.zoo_shading import unit

__all__ = ["RandomScene", "random_scene", "make_random_case", "scene_truth", "SEED_BASE", "VARIATIONS"]

SEED_BASE = 41_000  # apart from the zoo's scene seeds (0–18)
SURFACES = ("flat", "bumpy", "embossed")
LIGHTINGS = ("flash", "dome", "directional")
LIGHT_ERRORS = ("none", "flash", "jitter")  # capture.json's lights: exact, all moved alike, each its own way
CLIPS = ("none", "channel", "processed")
#: every variation and its values (the tests check each value is drawn across seeds)
VARIATIONS = {"materials": (1, 2, 3), "lobe": ("phong", "blinn", "ggx_full"), "gloss": (False, True),
              "spec_colour": ("white", "metal"), "surface": SURFACES, "given_normals": (False, True),
              "lighting": LIGHTINGS, "light_error": LIGHT_ERRORS, "encoding": ("srgb8", "linear16", "float"),
              "clip": CLIPS, "flakes": ("none", "uniform", "left")}
METAL = (1.0, 0.78, 0.45)  # a gold-like specular colour (relative)
FLASH_OFFSET_M = (0.012, 0.03)  # the flash's distance from the lens (and a dome's common error), metres
JITTER_M = 0.01  # per-shot light-position error σ per axis, metres


@dataclass(frozen=True)
class RandomScene:
    """One drawn capture: the zoo :class:`~torchmetal.synth.zoo_render.Scene` it renders from (size, shots,
    lobe, s, α, encoding, exposure, flakes, scene seed) and the variations the zoo's Scene does not hold.

    ``materials``: Voronoi regions, each (s, α, texture factor); ``gloss``: smooth s, α maps on top;
    ``spec_colour``: (3,) relative specular colour; ``surface`` with ``given_normals`` (normals.npy written);
    ``lighting`` (its zoo layout in ``scene.layout`` for dome / directional); ``light_error`` of capture.json's
    lights; ``shot_noise``, ``read_noise``: σ = shot·√I + read (linear); ``clip``.
    """

    seed: int
    scene: Scene
    materials: tuple[tuple[float, float, float], ...]
    gloss: bool
    spec_colour: tuple[float, float, float]
    surface: str
    given_normals: bool
    lighting: str
    light_error: str
    shot_noise: float
    read_noise: float
    clip: str

    @property
    def name(self) -> str:
        return self.scene.name

    def describe(self) -> dict:
        """The variations as a flat JSON-able dict."""
        sc = self.scene
        flakes = "none" if sc.flakes is None else sc.flakes.get("region") or "uniform"
        return {"seed": self.seed, "size": sc.size, "shots": sc.shots, "materials": len(self.materials),
                "lobe": sc.lobe, "gloss": self.gloss,
                "spec_colour": "white" if len(set(self.spec_colour)) == 1 else "metal", "surface": self.surface,
                "given_normals": self.given_normals, "lighting": self.lighting, "layout": sc.layout,
                "light_error": self.light_error, "encoding": sc.encoding, "shot_noise": self.shot_noise,
                "read_noise": self.read_noise, "clip": self.clip, "flakes": flakes, "s": sc.s, "alpha": sc.alpha}

    def variation(self, key: str):
        return self.describe()[key]


def _pick(rng: np.random.Generator, options, p=None):
    return options[int(rng.choice(len(options), p=p))]


def random_scene(seed: int) -> RandomScene:
    """The capture of draw ``seed`` (deterministic): every variation of the module docstring."""
    rng = np.random.default_rng([SEED_BASE, seed])
    lobe = _pick(rng, ("phong", "blinn", "ggx_full"), (0.45, 0.25, 0.30))
    n_mat = _pick(rng, (1, 2, 3), (0.55, 0.3, 0.15))
    # (s, α, texture factor) per material; the first one is the scene's global s, α
    mats = []
    for i in range(n_mat):
        s = float(rng.uniform(0.15, 0.8) if lobe != "ggx_full" else rng.uniform(0.1, 0.4))
        alpha = float(np.exp(rng.uniform(np.log(15.0), np.log(400.0))))
        mats.append((s, alpha, 1.0 if i == 0 else float(rng.uniform(0.3, 0.8))))
    if n_mat > 1:  # materials that differ: gloss at least ×3 apart from the first
        mats = [mats[0]] + [(s, mats[0][1] * float(rng.choice([1 / 6, 1 / 3, 3, 6])), t) for s, _, t in mats[1:]]
    gloss = bool(rng.random() < 0.2)
    colour = METAL if rng.random() < 0.3 else (1.0, 1.0, 1.0)
    surface = _pick(rng, SURFACES, (0.5, 0.25, 0.25))
    given = bool(surface != "flat" and rng.random() < 0.35)
    lighting = _pick(rng, LIGHTINGS, (0.35, 0.4, 0.25))
    if lighting == "directional":
        layout, camera, light_error = "directional", _pick(rng, ("ortho", "jitter")), "none"
    else:
        layout = "hemisphere" if lighting == "flash" else _pick(rng, ("ring", "hemisphere"))
        camera = "fixed" if lighting == "flash" else "jitter"
        light_error = _pick(rng, LIGHT_ERRORS, (0.5, 0.35, 0.15))
    encoding = _pick(rng, ("srgb8", "linear16", "float"), (0.45, 0.35, 0.2))
    if encoding == "float" and rng.random() < 0.4:
        shot, read = 0.0, 0.0
    else:
        shot, read = float(rng.uniform(0.003, 0.02)), float(rng.uniform(0.0, 0.003))
    clip = _pick(rng, CLIPS, (0.6, 0.25, 0.15)) if encoding != "float" else "none"
    # clipped scenes exposed so that the highlights' cores clip, not whole highlights (at ×2–3.5 a 6-shot scene's
    # every highlight observation clipped and the fit kept no specular lobe: 3 of the first 4 scenes, 2026-12-06)
    exposure = float(rng.uniform(0.8, 1.2) if clip == "none" else rng.uniform(1.3, 2.2))
    flakes = None
    flake_kind = _pick(rng, ("none", "uniform", "left"), (0.75, 0.17, 0.08))
    if flake_kind != "none":
        flakes = {"density": float(rng.uniform(0.02, 0.035)), "area_median": float(rng.uniform(2.0, 4.5)),
                  "area_log_std": 0.3, "aspect": (0.5, 1.0), "tilt_sigma": float(rng.uniform(0.1, 0.2)),
                  "glint_sigma": float(rng.uniform(0.03, 0.05)),
                  "color": tuple(float(c) for c in rng.uniform(0.5, 0.95, 3))}
        if flake_kind == "left":
            flakes["region"] = "left"
    size = 48 if flakes is not None else int(rng.choice([32, 40]))
    shots = int(rng.integers(7, 10)) if flakes is not None else int(rng.integers(6, 9))
    texture = _pick(rng, ("procedural", "highfreq", "photo:coffee", "photo:chelsea"), (0.7, 0.1, 0.1, 0.1))
    sc = Scene(f"random_{seed:04d}", size=size, shots=shots, held=3, layout=layout, camera=camera, texture=texture,
               lobe=lobe, s=mats[0][0], alpha=mats[0][1], flakes=flakes, encoding=encoding, noise=shot,
               exposure=exposure, seed=SEED_BASE + seed)
    return RandomScene(seed=seed, scene=sc, materials=tuple(mats), gloss=gloss, spec_colour=colour, surface=surface,
                       given_normals=given, lighting=lighting, light_error=light_error, shot_noise=shot,
                       read_noise=read, clip=clip)


# ---------------------------------------------------------------------------- truth


def embossed_normals(n: int, rng: np.random.Generator, max_slope: float = 0.35) -> np.ndarray:
    """(3, n, n) unit normals of an embossing: raised discs and bars with soft (1.5 px) edges on a flat plane."""
    import cv2

    h = np.zeros((n, n), np.float32)
    for _ in range(int(rng.integers(3, 7))):
        cx, cy = rng.uniform(0.1, 0.9, 2) * n
        if rng.random() < 0.5:
            cv2.circle(h, (int(cx), int(cy)), int(rng.uniform(0.06, 0.18) * n), 1.0, -1)
        else:
            w, l = rng.uniform(0.04, 0.08) * n, rng.uniform(0.2, 0.5) * n
            ang = rng.uniform(0, 180)
            box = cv2.boxPoints(((float(cx), float(cy)), (float(l), float(w)), float(ang))).astype(np.int32)
            cv2.fillPoly(h, [box], 1.0)
    h = cv2.GaussianBlur(h, (0, 0), 1.5).astype(np.float64)
    gy, gx = np.gradient(h)
    scale = max_slope / max(float(np.abs(np.stack([gx, gy])).max()), 1e-12)
    nn = np.stack([-gx * scale, gy * scale, np.ones_like(gx)])  # row index runs towards −y
    return unit(nn)


def _regions(n: int, k: int, rng: np.random.Generator) -> np.ndarray:
    """(n, n) int: Voronoi regions of ``k`` random centres (0 everywhere for k = 1)."""
    if k == 1:
        return np.zeros((n, n), int)
    c = rng.uniform(0, n, (k, 2))
    yy, xx = np.mgrid[0:n, 0:n] + 0.5
    d = (xx[None] - c[:, 0, None, None]) ** 2 + (yy[None] - c[:, 1, None, None]) ** 2
    return np.argmin(d, 0)


def random_truth(rs: RandomScene) -> Truth:
    """The zoo's truth of ``rs.scene`` (texture, flakes) with this scene's materials, gloss maps, specular
    colour and surface."""
    sc = rs.scene
    n = sc.size
    truth = make_truth(sc)
    rng = _rng(sc.seed, 10)
    if rs.surface == "bumpy":
        truth.normals = make_normals("bumpy", n, _rng(sc.seed, 11), max_slope=float(rng.uniform(0.15, 0.3)))
    elif rs.surface == "embossed":
        truth.normals = embossed_normals(n, _rng(sc.seed, 11))
    region = _regions(n, len(rs.materials), _rng(sc.seed, 12))
    s = np.zeros((n, n))
    alpha = np.zeros((n, n))
    tex_f = np.zeros((n, n))
    for i, (si, ai, ti) in enumerate(rs.materials):
        s[region == i], alpha[region == i], tex_f[region == i] = si, ai, ti
    if rs.gloss:  # smooth maps: α over ×0.4–×2.5, s over ×0.6–×1.4
        g = _smooth(_rng(sc.seed, 13), 2, n, n, 4)
        alpha = alpha * np.exp(0.9 * (2 * g[0] - 1))
        s = s * (0.6 + 0.8 * g[1])
    colour = np.asarray(rs.spec_colour, dtype=np.float64)
    truth.s = colour[:, None, None] * s[None]
    truth.alpha = np.broadcast_to(alpha[None], (3, n, n)).copy()
    truth.texture = truth.texture * tex_f[None]
    if truth.flakes is not None:  # the flakes sit on the surface drawn here
        truth.flakes["world_normal"] = flake_normals(truth)
    return truth


def _flash_layout(rs: RandomScene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A phone held level over the sample, its flash a fixed offset beside the lens: lights (K, 4), cameras
    (K, 4), exposure factors (K,) and the offset (3,)."""
    k = rs.scene.shots + rs.scene.held
    r = rng.uniform(*FLASH_OFFSET_M)
    ang = rng.uniform(0, 2 * math.pi)
    offset = np.array([r * math.cos(ang), r * math.sin(ang), 0.0])
    cams = np.zeros((k, 4))
    for i in range(k):
        cams[i] = [*rng.uniform(-0.06, 0.06, 2), CAMERA_HEIGHT * rng.uniform(0.7, 1.1), 1.0]
    lights = cams.copy()
    lights[:, :3] += offset
    return lights, cams, rng.uniform(0.85, 1.15, k), offset


def _capture_lights(rs: RandomScene, lights: np.ndarray, cams: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The lights capture.json states: the true ones, or off by the flash's one move (a flash layout: at the
    lens) or by per-shot jitter."""
    out = lights.copy()
    point = out[:, 3] == 1
    if rs.light_error == "flash":
        if rs.lighting == "flash":
            out[point, :3] = cams[point, :3]  # the capture put the flash at the lens
        else:
            r, ang = rng.uniform(*FLASH_OFFSET_M), rng.uniform(0, 2 * math.pi)
            out[point, :3] += np.array([r * math.cos(ang), r * math.sin(ang), rng.uniform(-0.3, 0.3) * r])
    elif rs.light_error == "jitter":
        out[point, :3] += rng.normal(0.0, JITTER_M, (int(point.sum()), 3))
    return out


def _encode(img: np.ndarray, rs: RandomScene, rng: np.random.Generator) -> np.ndarray:
    """(3, n, n) linear → stored (n, n, 3): shot + read noise, the clip (processed: a pixel with a clipped
    channel has its other channels raised by the overflow, as a phone's highlight roll-off whitens it),
    quantised as the encoding says."""
    noisy = img + (rs.shot_noise * np.sqrt(np.clip(img, 0, None)) + rs.read_noise) * rng.normal(size=img.shape)
    if rs.clip == "processed":
        over = np.clip(noisy.max(0, keepdims=True) - 1.0, 0.0, None)
        noisy = noisy + over
    hwc = noisy.transpose(1, 2, 0)
    enc = rs.scene.encoding
    if enc == "srgb8":
        return np.round(srgb_encode(hwc) * 255.0).astype(np.uint8)
    if enc == "linear16":
        return np.round(np.clip(hwc, 0.0, 1.0) * 65535.0).astype(np.uint16)
    return np.clip(hwc, 0.0, None).astype(np.float32)


def make_random_case(rs: RandomScene, out_dir: str | os.PathLike) -> ZooCase:
    """Render ``rs`` and write its capture directory under ``out_dir`` (created): fit shots with capture.json's
    (possibly wrong) lights; the held-out shots' clean renders use the true lights."""

    sc = rs.scene
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    truth = random_truth(rs)
    rng = _rng(sc.seed, 3)
    if rs.lighting == "flash":
        lights, cams, factor, _ = _flash_layout(rs, rng)
    else:
        lights, cams, factor = make_layout(sc, rng)
    told = _capture_lights(rs, lights, cams, _rng(sc.seed, 14))
    tex_mean = float(truth.texture.mean())
    ints = np.stack([_intensity(lights[i], tex_mean, sc.exposure, factor[i]) for i in range(len(lights))])
    noise_rng = _rng(sc.seed, 4)
    write_capture_dir(out, truth, sc.shots, lights, ints, cams, encoding=sc.encoding,
                      encode=lambda img: _encode(img, rs, noise_rng), normals=rs.given_normals, capture_lights=told)
    held = slice(sc.shots, sc.shots + sc.held)
    clean = np.stack([render_clean(truth, lights[i], ints[i], cams[i]) for i in range(sc.shots, len(lights))])
    stats = {"s": float(np.mean(truth.s)), "alpha": float(np.exp(np.mean(np.log(truth.alpha))))}
    return ZooCase(scene=sc, capture_dir=out, truth=truth, held_lights=lights[held], held_intensities=ints[held],
                   held_cameras=cams[held], clean=clean.astype(np.float32), fit_lights=told[:sc.shots],
                   fit_intensities=ints[:sc.shots], fit_cameras=cams[:sc.shots], truth_stats=stats,
                   flake_pixels=flake_pixels(truth))


# ---------------------------------------------------------------------------- what each choice should do

REFERENCE, EXTENSION, NA = "reference", "extension", "n/a"


def scene_truth(rs: RandomScene) -> dict[str, str]:
    """Per choice (its ``Decision`` name), whether the truth is the reference, the extension or neither.

    - registration: reference ("off": the generator never moves a shot).
    - clipping: a processed clip (the pixel's other channels wrong) → extension ("pixel"); else reference.
    - normals, relief: normals.npy given → n/a (the capture's own are kept); flat → reference; bumpy or
      embossed → extension (relief: embossed; a smooth bump is the estimate's, n/a for the relief).
    - light: capture.json exact → reference; the flash's one move → extension; per-shot jitter → n/a
      (no candidate models it); directional lights → reference.
    - weights: noise-free → reference; else n/a (both estimate the same model).
    - lobe: Phong → reference; Blinn or GGX → extension.
    - specular evidence: reference ("specular": every scene has a specular lobe; the extension drops it).
    - specular clusters: 2–3 materials → extension; one without gloss maps → reference; else n/a.
    - gloss maps: gloss maps → extension; one material without → reference; else n/a.
    - specular colour: a metal's colour → reference ("free"); white → extension ("white").
    - flakes, observed flakes: flakes → extension (observed: n/a); none → reference.
    - density map: flakes on one half → extension; uniform → reference; none → n/a.
    - relabel: n/a.
    """
    sc = rs.scene
    if rs.given_normals:
        normals = relief = NA
    elif rs.surface == "flat":
        normals = relief = REFERENCE
    else:
        normals, relief = EXTENSION, EXTENSION if rs.surface == "embossed" else NA
    if rs.lighting == "directional" or rs.light_error == "none":
        light = REFERENCE
    else:
        light = EXTENSION if rs.light_error == "flash" else NA
    n_mat = len(rs.materials)
    flakes = sc.flakes is not None
    return {
        "registration": REFERENCE,
        "clipping": EXTENSION if rs.clip == "processed" else REFERENCE,
        "normals": normals,
        "relief": relief,
        "light": light,
        "weights": REFERENCE if rs.shot_noise == 0 and rs.read_noise == 0 else NA,
        "lobe": REFERENCE if sc.lobe == "phong" else EXTENSION,
        "specular evidence": REFERENCE,
        "specular clusters": EXTENSION if n_mat > 1 else (REFERENCE if not rs.gloss else NA),
        "gloss maps": EXTENSION if rs.gloss else (REFERENCE if n_mat == 1 else NA),
        "specular colour": REFERENCE if len(set(rs.spec_colour)) > 1 else EXTENSION,
        "relabel": NA,
        "flakes": EXTENSION if flakes else REFERENCE,
        "observed flakes": NA if flakes else REFERENCE,
        "density map": NA if not flakes else (EXTENSION if sc.flakes.get("region") else REFERENCE),
    }


def with_size(rs: RandomScene, size: int, shots: int | None = None) -> RandomScene:
    """The same draw at another size (tests)."""
    return replace(rs, scene=rs.scene.with_(size=size, shots=shots or rs.scene.shots))
