"""Texture encoding: the specular encoding reproduces F0 and F90, PNGs round trip."""

import numpy as np
import torch

from tests.formats.kinds import make_material
from torchmetal.formats.engine import engine_material
from torchmetal.formats.textures import (
    MAX_F0_IOR,
    decode_png,
    f0_to_ior,
    png_bytes,
    specular_encoding,
    to_linear,
    to_srgb,
)


def test_specular_encoding_reproduces_f0_and_f90():
    em = engine_material(make_material("flat-clustered-noflakes"))
    enc = specular_encoding(em)
    f0_ior = ((enc["ior"] - 1) / (enc["ior"] + 1)) ** 2
    f90 = enc["specular_factor"] * enc["f90_map"]
    f0 = (f0_ior * enc["color_factor"] * enc["color_map"]).clamp(max=1.0) * f90
    torch.testing.assert_close(f90.float(), em.f90, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(f0.float(), em.f0, rtol=1e-5, atol=1e-9)
    assert float(enc["color_map"].max()) <= 1.0
    top = float((em.f0 / em.f90).max())  # F0/F90 near 1 (no Fresnel rise): the IOR caps at MAX_F0_IOR
    assert enc["color_factor"] == (1.0 if top <= MAX_F0_IOR else __import__("pytest").approx(top / MAX_F0_IOR, rel=1e-5))


def test_ior_of_f0():
    assert abs(f0_to_ior(0.04) - 1.5) < 1e-12
    assert ((f0_to_ior(0.99) - 1) / (f0_to_ior(0.99) + 1)) ** 2 == __import__("pytest").approx(MAX_F0_IOR)


def test_png_round_trip():
    g = np.random.default_rng(0)
    x = g.random((5, 7, 4))
    back = decode_png(png_bytes(x))
    assert back.shape == (5, 7, 4) and np.abs(back - x).max() <= 0.5 / 255 + 1e-12
    lin = g.random((4, 4, 3))
    assert np.abs(to_linear(to_srgb(lin)) - lin).max() < 1e-6
