"""The material renderer: Phong shading plus deterministic sparkles, as an ``nn.Module``.

``MaterialRenderer(material)(light (B,4), light_intensity (B,3), camera (B,4)) -> (B,3,H,W)``
computes exactly the model of :func:`torchmetal.phong.phong_render` plus
:func:`torchmetal.flakes.model.field.sparkle_render` (to float32 rounding), but is written for speed
and for a small ONNX graph (docs/design.md §2.4):

- **Only what the material uses is in the graph.** No flake ops when the material has no flakes
  (or ``flakes=False``); global ``(3,)`` specular terms stay scalars per channel, clustered
  specular is stored as a ``uint8`` label map plus a ``(3, K)`` table (the ``(3, H, W)`` maps are
  gathered once: cached buffers in eager mode, constant-folded by onnxruntime at session load).
- **Everything light-independent is precomputed.** The surface is the plane z = 0, so a pixel's
  offset to a light or camera is separable: ``x − w·X`` depends on the column only and
  ``y − w·Y`` on the row only. Only the pixel-centre coordinate vectors ``(W,)`` and ``(H,)`` are
  stored, never a dense ``(3, H, W)`` point map.
- **Flat normals are folded.** With n = (0, 0, 1) (``material.normals`` is None or all
  (0, 0, 1)), n·l = l_z, the mirror direction is (−l_x, −l_y, l_z) and "lit" (n·l > 0) is one
  boolean per shot, so the dense work is a handful of single-channel maps. Other normals take a
  general per-pixel path.
- **Sparse sparkles.** The flake field is baked once; only the pixels with a non-zero flake
  footprint (a few % of the texture) are kept, as flat indices plus their flake normal and
  weighted colour. Their glints are shaded with the flake module's own
  :func:`~torchmetal.flakes.model.field.sparkle_shading` at those points only and scatter-added into
  the Phong image. If the footprint covers more than a quarter of the texture, dense maps are
  used instead.

- **No per-pixel selects.** onnxruntime's ``Where`` costs about 20 ``Mul`` on a 1024² map, so
  masks are 0/1 factors of a single-channel weight (lit pixels of a bumpy surface, the exact
  horizon, seen pixels of GGX) and the lobe's log is clipped instead of masked (a lobe ≤ 1e-38
  past the horizon when every α ≥ 1; materials with some α < 1 get an exact mask). "Point vs
  directional light" is folded into the separable sums, and sparkles are scatter-added into the
  specular term so that the last op writes the output.

- **Lobes.** ``material.lobe`` "blinn" takes the Phong path with 1 − n·h in place of 1 − r·v;
  "ggx" evaluates :func:`torchmetal.lobes.ggx_lobe` as one fraction whose single-channel
  numerator carries the weights (:meth:`MaterialRenderer._ggx_spec`); its α-dependent part is
  single-channel work, once per channel or once when the channels share α. The half-vector
  terms use v·h = |l + v|/2 and, on flat surfaces, 1 − n·h without cancellation.

- **Channel-shared α** (global, per cluster or per pixel): the Phong/Blinn exp is one
  (B,1,H,W) map.

All state lives in buffers, so ``.to()``, ``state_dict`` and ONNX export need no extra code.
The specular lobe uses the same Kahan ``log1p`` form as :func:`torchmetal.phong.specular_lobe`
and only ops that export bit-for-bit or within a few ulp (no ``log1p``, no RNG, no ``pow``).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torchmetal.checks import check_finite, check_float, check_shape
from torchmetal.errors import InputError
from torchmetal.flakes.model.field import FlakeField, sparkle_shading
from torchmetal.flakes.model.observed import material_flake_field
from torchmetal.geometry import is_flat, shading_geometry, surface_points
from torchmetal.lobes import fresnel_ratio, ggx_k
from torchmetal.material import Material
from torchmetal.phong import channel_map

__all__ = ["MaterialRenderer", "DENSE_FLAKE_FRACTION"]

_EPS2 = 1e-24  # geometry._EPS ** 2: clamp of squared lengths before normalising
_TINY = 1.1754944e-38  # smallest normal float32
_BELOW_ONE = 1.0 - 2.0**-24  # largest float32 below 1
DENSE_FLAKE_FRACTION = 0.25  # above this footprint fraction the flake maps stay dense


def _split(target: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(B, 4) homogeneous vectors → four (B, 1, 1, 1) components x, y, z, w."""
    t = target.reshape(-1, 4, 1, 1)
    return t[:, 0:1], t[:, 1:2], t[:, 2:3], t[:, 3:4]


class MaterialRenderer(nn.Module):
    """Render a :class:`Material` for any batch of lights and cameras.

    Args:
        material: the fitted material.
        flakes: include the sparkle term when the material has flakes (default True).

    ``forward(light (B,4), light_intensity (B,3), camera (B,4)) -> (B,3,H,W)`` float32 linear
    radiance. Attributes: ``height``, ``width``, ``flat`` (normals folded), ``clustered``
    (per-pixel specular), ``lobe``, ``has_flakes``, ``flake_pixels`` (number of sparse flake
    pixels, or −1 for dense maps).
    """

    def __init__(self, material: Material, *, flakes: bool = True) -> None:
        super().__init__()
        if not isinstance(material, Material):
            raise InputError(f"material: expected a torchmetal Material, found {type(material).__name__}")
        m = material
        f32 = torch.float32
        dev = m.texture.device
        self.height, self.width = m.height, m.width
        self.size = (float(m.size[0]), float(m.size[1]))
        self.lobe = m.lobe
        self.register_buffer("texture", m.texture.detach().to(f32).clone())
        # pixel-centre coordinates, bit-identical to geometry.surface_points
        self.register_buffer("xs", surface_points(1, m.width, self.size, dtype=f32, device=dev)[0, 0].clone())
        self.register_buffer("ys", surface_points(m.height, 1, self.size, dtype=f32, device=dev)[1, :, 0].clone())

        self.flat = m.normals is None or is_flat(m.normals)
        if not self.flat:
            self.register_buffer("normals", m.normals.detach().to(f32).clone())

        self.clustered = m.clustered
        self.mapped = m.gloss_s is not None  # gloss maps: (3, H, W) s and α buffers
        if self.mapped:
            self.register_buffer("gloss_s", m.gloss_s.detach().to(f32).contiguous().clone())
            self.register_buffer("gloss_alpha", m.gloss_alpha.detach().to(f32).contiguous().clone())
            alpha_min = float(self.gloss_alpha.min())
        elif self.clustered:
            k = int(m.cluster_s.shape[0])
            lab_dtype = torch.uint8 if k <= 256 else torch.int32
            self.register_buffer("spec_labels", m.spec_labels.detach().to(dev).to(lab_dtype).clone())
            self.register_buffer("cluster_s", m.cluster_s.detach().to(f32).t().contiguous())  # (3, K)
            self.register_buffer("cluster_alpha", m.cluster_alpha.detach().to(f32).t().contiguous())
            s_map, a_map = self._gather_specular()
            self.register_buffer("_s_map", s_map, persistent=False)  # eager-mode cache
            self.register_buffer("_alpha_map", a_map, persistent=False)
            self.register_load_state_dict_post_hook(_refresh_specular_cache)
            alpha_min = float(self.cluster_alpha.min())
        else:
            self.register_buffer("s", m.s.detach().to(f32).clone())
            self.register_buffer("alpha", m.alpha.detach().to(f32).clone())
            alpha_min = float(self.alpha.min())
        # one exponent for all channels (per pixel or global): the lobe is a (B,1,H,W) map
        alpha_tab = self.gloss_alpha if self.mapped else self.cluster_alpha if self.clustered else self.alpha
        self.alpha_uniform = bool((alpha_tab == alpha_tab[0:1]).all())
        # With α ≥ 1 the clipped log-lobe past the horizon gives a lobe ≤ 1e-38; smaller
        # exponents get an exact zero there (two more single-channel ops).
        self.exact_horizon = not alpha_min >= 1.0 and self.lobe != "ggx"  # GGX: no clipped log-lobe

        self.has_flakes = bool(flakes and m.flakes is not None)
        self.flake_pixels = 0
        if self.has_flakes:
            self._bake_flakes(m)

    # ----------------------------------------------------------------------------------- setup
    def _gather_specular(self) -> tuple[Tensor, Tensor]:
        lab = self.spec_labels.long()
        return self.cluster_s[:, lab], self.cluster_alpha[:, lab]

    def _bake_flakes(self, m: Material) -> None:
        normals = m.flat_normals().detach().to(torch.float32)
        f = material_flake_field(m.flakes, m.observed_flakes, m.height, m.width, normals, self.size)
        self.glint_sigma = float(f.glint_sigma)
        wc = (f.weight * f.color).to(torch.float32)  # (3, H, W) footprint × colour
        keep = (f.weight[0] > 0) & (wc.abs().sum(0) > 0)
        n_px = int(keep.sum())
        if n_px == 0:
            self.has_flakes = False
            return
        if n_px > DENSE_FLAKE_FRACTION * m.height * m.width:
            self.flake_pixels = -1
            self.register_buffer("flake_wc", wc.contiguous())
            self.register_buffer("flake_normal", f.normal.to(torch.float32).contiguous())
            return
        self.flake_pixels = n_px
        flat_idx = torch.nonzero(keep.reshape(-1), as_tuple=False).reshape(-1)  # row-major order
        rows, cols = flat_idx // m.width, flat_idx % m.width
        normal = f.normal.to(torch.float32)
        self.register_buffer("flake_index", flat_idx.to(torch.int64))  # (N,) into H·W
        self.register_buffer("flake_points", torch.stack([self.xs[cols], self.ys[rows], torch.zeros_like(self.xs[cols])]).view(3, 1, n_px))
        self.register_buffer("flake_wc", wc[:, rows, cols].reshape(3, 1, n_px).contiguous())
        self.register_buffer("flake_normal", normal[:, rows, cols].reshape(3, 1, n_px).contiguous())
        if not self.flat:
            self.register_buffer("flake_surface_normal", normals[:, rows, cols].reshape(3, 1, n_px).contiguous())

    def extra_repr(self) -> str:
        return (
            f"{self.height}x{self.width}, flat={self.flat}, clustered={self.clustered}, maps={self.mapped}, lobe={self.lobe}, "
            f"flakes={'off' if not self.has_flakes else ('dense' if self.flake_pixels < 0 else f'{self.flake_pixels} px')}"
        )

    # --------------------------------------------------------------------------------- forward
    def forward(self, light: Tensor, light_intensity: Tensor, camera: Tensor) -> Tensor:
        dtype = self.texture.dtype
        light, light_intensity, camera = light.to(dtype), light_intensity.to(dtype), camera.to(dtype)
        (ux, uy, uz), (wx, wy, wz), lz, inv_d2 = self._unit_vectors(light, camera)
        n_dot_l, (ex, ey, ez), lit, weight = self._reflection(ux, uy, uz, wx, wy, wz, lz, inv_d2)

        shade = light_intensity.reshape(-1, 3, 1, 1)  # (B,3,1,1)
        q_spec = (shade if lit is None else shade * lit)
        # outer products (B,3,H,W); flat: max(n·l, 0) = l_z/|l|·[l_z > 0], the factor is in q_spec
        q_diffuse = shade * (n_dot_l.clamp_min(0.0) * inv_d2) if lit is None else q_spec * (n_dot_l * inv_d2)
        if self.lobe == "ggx":
            spec = self._ggx_spec(*self._half_terms(ux, uy, uz, wx, wy, wz), n_dot_l, weight, q_spec)
        else:
            if self.lobe == "phong":
                yq = -0.5 * (ex * ex + ey * ey + ez * ez)
            else:  # blinn: the same log-lobe of n·h
                yq = -self._half_terms(ux, uy, uz, wx, wy, wz)[0]
            spec = self._log1p_lobe_spec(yq, weight, q_spec)
        if self.has_flakes:
            # sparkles are added into the specular term, so the last op writes the output
            # directly (onnxruntime copies a reshape that produces a graph output)
            spec = self._add_sparkle(spec, light, light_intensity, camera)
        return self.texture * q_diffuse + spec

    def _unit_vectors(self, light: Tensor, camera: Tensor) -> tuple[tuple[Tensor, Tensor, Tensor],
                                                                    tuple[Tensor, Tensor, Tensor], Tensor, Tensor]:
        """Unit l and v components at every pixel (separable broadcasting pieces), the light's z and the
        light's falloff 1/dist² (1 for directional lights)."""
        dtype = self.texture.dtype
        x = self.xs.view(1, 1, 1, -1)
        y = self.ys.view(1, 1, -1, 1)
        lx, ly, lz, lw = _split(light)
        vx, vy, vz, vw = _split(camera)
        # Separable offsets to the targets: (B,1,1,W) and (B,1,H,1); the z offset is the target's
        # own z (plane z = 0). Only the final sums are full (B,1,H,W) maps.
        dlx, dly = lx - lw * x, ly - lw * y
        dvx, dvy = vx - vw * x, vy - vw * y
        lx2, lyz2 = dlx * dlx, dly * dly + lz * lz
        nrm_l = torch.sqrt(lx2 + lyz2.clamp_min(_EPS2))
        nrm_v = torch.sqrt(dvx * dvx + (dvy * dvy + vz * vz).clamp_min(_EPS2))
        ux, uy, uz = dlx / nrm_l, dly / nrm_l, lz / nrm_l  # unit l
        wx, wy, wz = dvx / nrm_v, dvy / nrm_v, vz / nrm_v  # unit v
        # 1/dist² for point lights, 1 for directional ones, without a per-pixel select:
        # dist² = p·|d|² + (1 − p) with p = [w > 0.5] folded into the separable parts.
        point = (lw > 0.5).to(dtype)
        inv_d2 = 1.0 / (point * lx2 + (point * lyz2 + (1.0 - point)))
        return (ux, uy, uz), (wx, wy, wz), lz, inv_d2

    def _reflection(self, ux: Tensor, uy: Tensor, uz: Tensor, wx: Tensor, wy: Tensor, wz: Tensor, lz: Tensor,
                    inv_d2: Tensor) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor], Tensor | None, Tensor]:
        """n·l, r − v, the flat surface's lit factor (None with normals) and the specular weight."""
        dtype = self.texture.dtype
        if self.flat:
            # n = (0,0,1): n·l = l_z, r − v = (−l_x − v_x, −l_y − v_y, l_z − v_z), lit ⇔ light z > 0
            n_dot_l = uz
            ex, ey, ez = ux + wx, uy + wy, uz - wz
            lit = (lz > 0).to(dtype)  # (B,1,1,1), folded into the specular scale below
            weight = inv_d2
        else:
            nx, ny, nz = self.normals[0:1].unsqueeze(0), self.normals[1:2].unsqueeze(0), self.normals[2:3].unsqueeze(0)
            n_dot_l = nx * ux + ny * uy + nz * uz
            two_nl = 2.0 * n_dot_l
            ex, ey, ez = two_nl * nx - ux - wx, two_nl * ny - uy - wy, two_nl * nz - uz - wz
            # lit as a 0/1 factor of the specular weight, not a select: onnxruntime's Where costs
            # ~20 Muls on a 1024² map
            lit = None
            weight = inv_d2 * (n_dot_l > 0).to(dtype)
        return n_dot_l, (ex, ey, ez), lit, weight

    def _log1p_lobe_spec(self, yq: Tensor, weight: Tensor, q_spec: Tensor) -> Tensor:
        """The Phong/Blinn specular term (B,3,H,W) of y = −q (phong: −|r − v|²/2)."""
        # log of the lobe max(r·v, 0) with y = −q = −|r − v|²/2: log1p(y) in the Kahan form
        # y·log(u)/(u − 1), u = fl(1 + y). u is clipped to [tiny, 1 − 2⁻²⁴]: the upper clip only
        # touches u == 1 (then the ratio is 1 to 1 ulp), the lower one gives a log-lobe ≤ −87·|y|
        # past the horizon (r·v ≤ 0), i.e. a lobe ≤ 1e-38 for α ≥ 1 instead of selects.
        u = (1.0 + yq).clamp(_TINY, _BELOW_ONE)
        t = torch.log(u) * (yq / (u - 1.0))
        if self.exact_horizon:
            weight = weight * (yq > -1.0).to(self.texture.dtype)
        return self._log_lobe_spec(t, weight, q_spec)

    def _spec_terms(self) -> tuple[Tensor, Tensor]:
        """s (1,3,1,1) or (1,3,H,W) and α of the same shape, with 1 channel when ``alpha_uniform``."""
        s, alpha = self._specular_maps() if (self.clustered or self.mapped) else (self.s, self.alpha)
        alpha = channel_map(alpha)
        return channel_map(s), (alpha[:, 0:1] if self.alpha_uniform else alpha)

    def _log_lobe_spec(self, t: Tensor, weight: Tensor, q_spec: Tensor) -> Tensor:
        """q_spec·s·exp(α·t)·weight (B,3,H,W); global s is folded into the per-shot scale q_spec.

        t, weight (B,1,H,W) (weight may broadcast); q_spec (B,3,1,1). The exp is one (B,1,H,W)
        map when all channels share the exponent.
        """
        s, alpha = self._spec_terms()
        lobe = torch.exp(alpha * t) * weight
        if self.clustered or self.mapped:
            return s * lobe * q_spec
        return lobe * (q_spec * s)

    def _ggx_spec(self, hq: Tensor, n_dot_v: Tensor, v_dot_h: Tensor, n_dot_l: Tensor, weight: Tensor, q_spec: Tensor) -> Tensor:
        """q_spec·s·ggx_lobe(hq, n·l, n·v, v·h, α)·weight as one fraction, without selects: (B,3,H,W).

        :func:`torchmetal.lobes.ggx_lobe` = D̂·F̂·G₁(n·l)·G₁(n·v)/(n·v)·[n·v > 0] with
        D̂ = (k/(k + (1 − k)w))², G₁(x) = 2x/(x + √(k + (1 − k)x²)), written as
        s·k²·4·n·l·F̂·[n·v > 0] / ((k + (1 − k)w)²·(n·l + √…)·(n·v + √…)). The denominator is
        ≥ k³ > 0 for n·l, n·v clamped to [0, 1], so the [n·v > 0] factor zeroes unseen pixels
        exactly; the single-channel numerator carries the weight and the per-shot scale q_spec
        (B,3,1,1) joins s·k². The α-dependent denominator is one (B,1,H,W) map per channel
        (joined by a concat), or a single one when α is shared by the channels: on this CPU three
        single-channel passes cost less than one (B,3,H,W) broadcast pass. Geometry (B,1,H,W)
        (weight may broadcast).
        """
        s, alpha = self._spec_terms()
        k = ggx_k(alpha)  # (1, 1 or 3, 1 or H, 1 or W)
        hq = hq.clamp(0.0, 1.0)
        w = hq * (2.0 - hq)  # 1 − (n·h)², exact near the peak
        nl = n_dot_l.clamp(0.0, 1.0)
        nv = n_dot_v.clamp(0.0, 1.0)
        nl2, nv2 = nl * nl, nv * nv
        num = (4.0 * nl) * fresnel_ratio(v_dot_h) * (weight * (n_dot_v > 0).to(nl.dtype))

        def fraction(kc: Tensor) -> Tensor:
            k1 = 1.0 - kc
            d = kc + k1 * w
            return num / ((d * d) * (nl + torch.sqrt(kc + k1 * nl2)) * (nv + torch.sqrt(kc + k1 * nv2)))

        frac = fraction(k) if k.shape[1] == 1 else torch.cat([fraction(kc) for kc in k.split(1, dim=1)], 1)
        return (q_spec * (s * (k * k))) * frac

    def _half_terms(self, ux, uy, uz, wx, wy, wz) -> tuple[Tensor, Tensor, Tensor]:
        """1 − n·h, n·v and v·h from unit l and v components (broadcasting pieces).

        With S = l + v, h = S/|S| and v·h = |S|/2 (unit l, v). Flat n: 1 − n·h = 1 − S_z/|S| =
        (S_x² + S_y²)/(|S|² + S_z·|S|), without the cancellation of 1 − h_z near the peak; other
        normals: |n − h|²/2.
        """
        sx, sy, sz = ux + wx, uy + wy, uz + wz
        sxy = sx * sx + sy * sy
        hs = (sxy + sz * sz).clamp_min(_EPS2)
        norm = torch.sqrt(hs)
        v_dot_h = 0.5 * norm
        if self.flat:
            return sxy / (hs + sz * norm).clamp_min(_EPS2), wz, v_dot_h
        inv = 1.0 / norm
        nx, ny, nz = self.normals[0:1].unsqueeze(0), self.normals[1:2].unsqueeze(0), self.normals[2:3].unsqueeze(0)
        dx, dy, dz = nx - sx * inv, ny - sy * inv, nz - sz * inv
        return 0.5 * (dx * dx + dy * dy + dz * dz), nx * wx + ny * wy + nz * wz, v_dot_h

    def _specular_maps(self) -> tuple[Tensor, Tensor]:
        if self.mapped:
            return self.gloss_s, self.gloss_alpha
        if torch.compiler.is_exporting():
            # in the file: uint8 labels + (3, K) tables; onnxruntime folds the gather at load
            return self._gather_specular()
        return self._s_map, self._alpha_map

    def _add_sparkle(self, image: Tensor, light: Tensor, intensity: Tensor, camera: Tensor) -> Tensor:
        if self.flake_pixels < 0:  # dense maps
            normals = self.normals if not self.flat else _flat_like(self.texture)
            geom = shading_geometry(normals, light, intensity, camera, self.size)
            field = FlakeField(torch.ones_like(self.flake_normal[:1]), self.flake_normal, self.flake_wc, self.glint_sigma, 0)
            return image + sparkle_shading(field, geom)
        pts = self.flake_points  # (3, 1, N)
        normals = self.flake_surface_normal if not self.flat else _flat_like(pts)
        geom = shading_geometry(normals, light, intensity, camera, points=pts)
        field = FlakeField(torch.ones_like(self.flake_wc[:1]), self.flake_normal, self.flake_wc, self.glint_sigma, self.flake_pixels)
        glint = sparkle_shading(field, geom)  # (B, 3, 1, N)
        b = image.shape[0]
        flat = image.reshape(b, 3, self.height * self.width)
        index = self.flake_index.view(1, 1, -1).expand(b, 3, -1)
        flat = flat.scatter_add(2, index, glint.reshape(b, 3, -1))
        return flat.reshape(b, 3, self.height, self.width)

    # ----------------------------------------------------------------------------------- checks
    @staticmethod
    def check_inputs(light: Tensor, light_intensity: Tensor, camera: Tensor) -> None:
        """One-line :class:`InputError` for wrong shapes, dtypes or non-finite values."""
        for name, x, c in (("light", light, 4), ("light_intensity", light_intensity, 3), ("camera", camera, 4)):
            check_shape(x, ("B", c), name)
            check_float(x, name)
            check_finite(x, name)
        b = {light.shape[0], light_intensity.shape[0], camera.shape[0]}
        if len(b) != 1:
            raise InputError(
                f"batch: expected light, light_intensity and camera with the same B, found "
                f"{light.shape[0]}, {light_intensity.shape[0]}, {camera.shape[0]}"
            )


def _refresh_specular_cache(module: MaterialRenderer, incompatible_keys) -> None:
    """After ``load_state_dict``: rebuild the eager (3, H, W) specular maps from the labels."""
    s_map, a_map = module._gather_specular()
    module._s_map.copy_(s_map)
    module._alpha_map.copy_(a_map)


def _flat_like(ref: Tensor) -> Tensor:
    """(3, *ref.shape[1:]) normals (0, 0, 1)."""
    z = torch.zeros_like(ref[:1])
    return torch.cat([z, z, torch.ones_like(z)])
