"""The scene zoo: the scenes every fit change is scored on (generator: :mod:`torchmetal.synth.zoo_render`).

:data:`SCENES` holds each scene at full (bench) size; :func:`ci_scenes` the same scenes smaller,
for the test suite. The first five are the benchmark's original captures (an 8-bit sRGB photo, bumpy
16-bit linear, few highlights at 1024², a Blinn truth, sharp directional light); the rest cover the
space (lobes, encodings, layouts, shot counts, two materials, flakes, unidentifiable lobes).
"""

from __future__ import annotations

from torchmetal.synth.zoo_render import Scene, ZooCase, decode, make_case, oracle_render, render_clean

__all__ = ["Scene", "ZooCase", "make_case", "render_clean", "oracle_render", "decode", "SCENES", "ci_scenes",
           "full_scenes"]

# ---------------------------------------------------------------------------- the zoo

_FLAKES_A = {"density": 0.004, "area_median": 4.0, "area_log_std": 0.35, "aspect": (0.5, 1.0), "tilt_sigma": 0.12,
             "glint_sigma": 0.03, "color": (0.9, 0.8, 0.6)}
_FLAKES_B = {"density": 0.008, "area_median": 2.5, "area_log_std": 0.3, "aspect": (0.6, 1.0), "tilt_sigma": 0.2,
             "glint_sigma": 0.04, "color": (0.7, 0.75, 0.9)}

_FLAKES_HALF = {**_FLAKES_A, "density": 0.008, "region": "left"}
# bright grey flakes: their brightest glints clip (8-bit), the censoring the flake likelihood must model
_FLAKES_BRIGHT = {**_FLAKES_A, "color": (0.8, 0.8, 0.8)}

#: name → Scene at full (bench) size. The benchmark's original captures are the first five; then the rest of the space.
SCENES: dict[str, Scene] = {s.name: s for s in [
    Scene("photo_srgb8", size=384, shots=12, texture="photo:astronaut", layout="hemisphere", camera="jitter",
          s=0.5, alpha=60, noise=0.01),
    Scene("bumpy_lin16", size=512, shots=16, encoding="linear16", normals="bumpy", exposure=2.2, s=0.6, alpha=120,
          layout="ring", noise=0.01, seed=1),
    Scene("few_highlight", size=1024, shots=8, layout="few", s=0.5, alpha=80, noise=0.01, seed=2),
    Scene("blinn_truth", size=256, shots=10, lobe="blinn", s=0.5, alpha=50, layout="hemisphere", seed=3),
    Scene("directional_sharp", size=256, shots=16, layout="directional", camera="ortho", normals="bumpy", s=1.5,
          alpha=300, exposure=1.6, seed=4),
    Scene("dome72", size=150, shots=66, held=6, layout="dome", camera="ortho", normals="bumpy", s=0.4, alpha=40,
          seed=5),
    Scene("ggx_truth", size=256, shots=12, lobe="ggx", s=0.4, alpha=100, layout="ring", seed=6),
    # the renderer's own GGX (Fresnel and shadowing included): the truth is in the default's candidate set
    Scene("ggx_full_truth", size=256, shots=12, lobe="ggx_full", s=0.3, alpha=150, layout="hemisphere", normals="bumpy",
          seed=18),
    Scene("two_materials", size=256, shots=12, texture="photo:coffee", second=(1.2, 600.0), s=0.15, alpha=15,
          layout="hemisphere", seed=7),
    Scene("highfreq_noise3", size=256, shots=12, texture="highfreq", noise=0.03, layout="ring", s=0.5, alpha=80, seed=8),
    Scene("three_shots", size=256, shots=3, held=2, layout="ring", s=0.5, alpha=40, seed=9),
    Scene("float_clean", size=256, shots=10, encoding="float", noise=0.0, layout="hemisphere", s=0.7, alpha=200,
          seed=10),
    Scene("grazing_only", size=256, shots=10, layout="grazing", camera="ortho", s=0.5, alpha=60, seed=11),
    Scene("blind_peak", size=256, shots=10, layout="blind", s=0.6, alpha=150, seed=12),
    Scene("flakes_a", size=256, shots=16, layout="hemisphere", flakes=_FLAKES_A, s=0.4, alpha=60, seed=13),
    Scene("flakes_b", size=256, shots=16, layout="ring", flakes=_FLAKES_B, s=0.3, alpha=40, normals="bumpy", seed=14),
    # glitter on the left half only: the flake-density map must put the sparkles there
    Scene("flakes_half", size=256, shots=16, layout="hemisphere", flakes=_FLAKES_HALF, s=0.4, alpha=60, seed=17),
    # a sharp (GGX) lobe on curved normals under many directional lights, 16-bit, no flakes: a Phong fit's
    # misfit at each highlight's core leaves positive peaks that a plain screen and null test take for glints
    Scene("sphere_sharp72", size=150, shots=66, held=6, layout="dome", camera="ortho", normals="sphere",
          lobe="ggx", encoding="linear16", s=0.8, alpha=700, seed=16),
    # flakes on a textured orange base (a photo tinted to mean albedo (0.6, 0.3, 0.1))
    Scene("flakes_orange", size=256, shots=16, layout="hemisphere", texture="photo:coffee", tint=(0.6, 0.3, 0.1),
          flakes=_FLAKES_A, s=0.4, alpha=60, seed=17),
    Scene("photo_bumpy_noise2", size=256, shots=12, texture="photo:chelsea", normals="bumpy", noise=0.02,
          layout="ring", s=0.5, alpha=100, seed=15),
    # bright grey flakes (issue 41 item 7): hemisphere lights (far tilt tail) and a ring (every flake's mirror shot)
    Scene("flakes_bright_hemi", size=512, shots=12, layout="hemisphere", flakes=_FLAKES_BRIGHT, s=0.4, alpha=60, seed=24),
    Scene("flakes_bright_ring", size=512, shots=12, layout="ring", flakes=_FLAKES_BRIGHT, s=0.4, alpha=60, seed=25),
]}

_CI_SIZE = {"dome72": 96, "few_highlight": 192, "photo_srgb8": 160, "bumpy_lin16": 160,
            "flakes_bright_hemi": 256, "flakes_bright_ring": 256}


def full_scenes() -> list[Scene]:
    return list(SCENES.values())


def ci_scenes(size: int = 128) -> list[Scene]:
    """The zoo at CI size: same scenes, smaller images — except the flake scenes, which keep their full
    256² (smaller, too few flakes glint to estimate their density: docs/measurements.md)."""
    out = []
    for sc in SCENES.values():
        n = _CI_SIZE.get(sc.name, sc.size if sc.flakes is not None else size)
        out.append(sc.with_(size=min(sc.size, n)))
    return out
