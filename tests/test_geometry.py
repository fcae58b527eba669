"""Geometry against a float64 numpy reference, including grazing angles."""

import numpy as np
import pytest
import torch

from torchmetal.geometry import dot, grid_shading_terms, normalize, pixel_axes, shading_geometry, surface_points


def numpy_geometry(normals, light, intensity, camera, size):
    """Straight transcription of docs/design.md §2.1/2.2 in float64 numpy, one pixel at a time style."""
    _, h, w = normals.shape
    i, j = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    p = np.stack([((j + 0.5) / w - 0.5) * size[0], (0.5 - (i + 0.5) / h) * size[1], np.zeros((h, w))])
    out = []
    for L, I, C in zip(light, intensity, camera):
        dl = L[:3, None, None] - L[3] * p
        d2 = (dl**2).sum(0)
        l = dl / np.sqrt(d2)
        E = I[:, None, None] / (d2 if L[3] == 1 else np.ones((h, w)))
        dv = C[:3, None, None] - C[3] * p
        v = dv / np.linalg.norm(dv, axis=0)
        nl = (normals * l).sum(0)
        r = 2 * nl * normals - l
        rv = (r * v).sum(0)
        out.append((l, v, nl, rv, E))
    return out


def random_config(rng, b=6, h=5, w=7, grazing=False):
    n = rng.normal(size=(3, h, w)) * 0.3 + np.array([0, 0, 1.0])[:, None, None]
    n /= np.linalg.norm(n, axis=0)
    lights, cams = [], []
    for k in range(b):
        elev = np.deg2rad(rng.uniform(0.5, 3.0) if grazing else rng.uniform(10, 90))
        az = rng.uniform(0, 2 * np.pi)
        d = np.array([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])
        lights.append(np.r_[d * rng.uniform(0.3, 3.0), 1.0] if k % 2 else np.r_[d, 0.0])
        ce = np.deg2rad(rng.uniform(20, 90))
        cd = np.array([np.cos(ce) * np.cos(az + 2), np.cos(ce) * np.sin(az + 2), np.sin(ce)])
        cams.append(np.r_[cd * 0.5, 1.0] if k % 3 else np.r_[cd, 0.0])
    return n, np.array(lights), rng.uniform(0.1, 10, size=(b, 3)), np.array(cams)


@pytest.mark.parametrize("grazing", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_float64_reference(seed, grazing):
    rng = np.random.default_rng(seed)
    n, L, I, C = random_config(rng, grazing=grazing)
    size = (0.1, 0.08)
    g = shading_geometry(*(torch.from_numpy(x) for x in (n, L, I, C)), size)
    ref = numpy_geometry(n, L, I, C, size)
    for k, (l, v, nl, rv, E) in enumerate(ref):
        np.testing.assert_allclose(g.l[k].numpy(), l, atol=1e-6)
        np.testing.assert_allclose(g.v[k].numpy(), v, atol=1e-6)
        np.testing.assert_allclose(g.n_dot_l[k, 0].numpy(), nl, atol=1e-6)
        np.testing.assert_allclose(g.r_dot_v[k, 0].numpy(), rv, atol=1e-6)
        np.testing.assert_allclose(g.irradiance[k].numpy(), E, rtol=1e-6)


def test_float32_close_to_reference():
    rng = np.random.default_rng(5)
    n, L, I, C = random_config(rng, grazing=True)
    g = shading_geometry(*(torch.from_numpy(x).float() for x in (n, L, I, C)), (0.1, 0.1))
    ref = numpy_geometry(n, L, I, C, (0.1, 0.1))
    for k, (_, _, nl, rv, _) in enumerate(ref):
        np.testing.assert_allclose(g.n_dot_l[k, 0].numpy(), nl, atol=1e-6)
        np.testing.assert_allclose(g.r_dot_v[k, 0].numpy(), rv, atol=2e-6)


def test_surface_points_contract_and_rows():
    p = surface_points(4, 8, (2.0, 1.0))
    assert p.shape == (3, 4, 8)
    assert p[0, 0, 0].item() == pytest.approx((0.5 / 8 - 0.5) * 2.0)
    assert p[1, 0, 0].item() == pytest.approx((0.5 - 0.5 / 4) * 1.0)  # row 0 is +y
    assert torch.equal(surface_points(4, 8, (2.0, 1.0), rows=(1, 3)), p[:, 1:3])


def test_chunked_geometry_equals_full():
    rng = np.random.default_rng(3)
    n, L, I, C = (torch.from_numpy(x) for x in random_config(rng, h=6))
    full = shading_geometry(n, L, I, C, (0.1, 0.1))
    pts = surface_points(6, 7, (0.1, 0.1), rows=(2, 5), dtype=n.dtype)
    part = shading_geometry(n[:, 2:5], L, I, C, points=pts)
    assert torch.equal(part.spec_q, full.spec_q[..., 2:5, :])
    assert torch.equal(part.irradiance, full.irradiance[..., 2:5, :])


def test_normalize_zero_vector_is_finite():
    x = torch.zeros(3, 2, 2)
    assert torch.equal(normalize(x, dim=0), x)
    assert dot(torch.ones(1, 3, 2, 2), torch.ones(1, 3, 2, 2)).shape == (1, 1, 2, 2)


def test_half_vector_unit():
    rng = np.random.default_rng(0)
    g = shading_geometry(*(torch.from_numpy(x) for x in random_config(rng)), (0.1, 0.1))
    np.testing.assert_allclose(g.half.norm(dim=1).numpy(), 1.0, atol=1e-12)


@pytest.mark.parametrize("flat", [False, True])
@pytest.mark.parametrize("seed", [0, 1])
def test_grid_shading_terms_match_shading_geometry(seed, flat):
    rng = np.random.default_rng(seed)
    n, L, I, C = (torch.from_numpy(x) for x in random_config(rng, grazing=seed == 1))
    if flat:
        n = torch.zeros_like(n)
        n[2] = 1.0
    size = (0.1, 0.08)
    g = shading_geometry(n, L, I, C, size)
    rows, cols = slice(1, 5, 2), slice(0, 7, 3)  # a strided sub-grid
    x, y = pixel_axes(5, 7, size, rows=rows, cols=cols, dtype=n.dtype)
    nl, q, dist2 = grid_shading_terms(L, C, x, y, None if flat else n[:, rows, cols])
    assert nl.shape == q.shape == dist2.shape == (L.shape[0], 2, 3)
    torch.testing.assert_close(nl, g.n_dot_l[:, 0, rows, cols], rtol=0, atol=1e-12)
    torch.testing.assert_close(q, g.spec_q[:, 0, rows, cols], rtol=0, atol=1e-12)
    torch.testing.assert_close(I[:, :, None, None] / dist2.unsqueeze(1), g.irradiance[..., rows, cols], rtol=1e-12, atol=0)


def test_pixel_axes_are_the_surface_points():
    p = surface_points(6, 5, (2.0, 1.0))
    x, y = pixel_axes(6, 5, (2.0, 1.0))
    assert torch.equal(x, p[0, 0]) and torch.equal(y, p[1, :, 0])
    x2, y2 = pixel_axes(6, 5, (2.0, 1.0), rows=slice(1, None, 2), cols=slice(3, 4))
    assert torch.equal(x2, x[3:4]) and torch.equal(y2, y[1::2])
