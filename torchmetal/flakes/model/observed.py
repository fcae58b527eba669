"""The sample's own flakes: flakes seen glinting in the fit shots, kept where they are.

The statistical field (:mod:`torchmetal.flakes.model.field`) draws flakes at random, so a held-out shot
of the same sample shows its glints where the field has none, and the field glints where the
photo does not: on the zoo's flake scenes that rendered 2–4 dB worse than no flakes at all. Here
each associated flake of the flake stage keeps its position, footprint, normal and colour
(:class:`ObservedFlakes`, measured by :func:`~torchmetal.flakes.estimate.observed_flakes.observed_flakes`).

:func:`material_flake_field` renders them with the statistical field filling only what no fit
shot observed: a statistical flake is dropped where it overlaps an observed one, and where some
fit shot would have detected it, had it been there: its peak glint amplitude (channel-mean colour ×
footprint peak) times that shot's glint factor exp(−|m − h|² / 2σ_g²) reaches ``detect_amp``, the
amplitude the fit shots' detector fires at (the least SNR of the detections × their median local σ).
The fit shots find flakes far off their glint peak: on zoo flakes_b (256²) every true flake whose
best fit-shot glint factor was ≥ 0.1 was observed (18 of 19 in [0.05, 0.1)), so the former fixed
cut at a factor of ``PROBED_GLINT`` = 0.5 (kept now only for observed flakes saved without
``detect_amp``) refilled that whole band with random flakes, which glinted in held-out views
between the fit shots: 58 of the 65 predicted sparkles with no true glint within 2 px came from
the fill (count ratio 1.28). With a coarse density map (glitter on part of the sample)
the fill is thinned cell by cell. Pixels beyond the observed sample (a tiled texture) are all
fill. Everything is light-independent and deterministic, so the renderer bakes it once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchmetal.errors import MaterialError
from torchmetal.flakes.model.field import FlakeField, field_cell, flake_field, hash_uniform
from torchmetal.flakes.model.filters import max_filter
from torchmetal.flakes.model.params import MAX_COLOR, FlakeModel
from torchmetal.geometry import shading_geometry

__all__ = ["ObservedFlakes", "observed_field", "material_flake_field", "footprints", "PROBED_GLINT", "ARRAYS"]

PROBED_GLINT = 0.5  # without ``detect_amp``: glint factor at which a fit shot would have seen a flake

#: array name → (attribute, file name): the material directory's files (docs/design.md §2.3)
ARRAYS = {
    "position": "flakes_position.npy", "axes": "flakes_axes.npy", "angle": "flakes_angle.npy",
    "normal": "flakes_normal.npy", "color": "flakes_color.npy", "probe_lights": "flakes_probe_lights.npy",
    "probe_cameras": "flakes_probe_cameras.npy", "density": "flakes_density.npy",
}



@dataclass
class ObservedFlakes:
    """The J flakes the fit shots saw, float32 tensors.

    position (J, 2) centre (row, col) in px; axes (J, 2) semi-major, semi-minor (px, the
    field's ellipse before its anti-aliasing shrink); angle (J,) radians from +col towards up;
    normal (J, 3) unit world flake normal; color (J, 3) linear glint reflectance;
    probe_lights, probe_cameras (N, 4): the fit shots (whose glints were looked for);
    density (gh, gw) coarse flake density relative to the sample mean, or None (uniform);
    shape (H, W): the texture they were observed on; detect_amp: the peak glint amplitude
    (channel mean, reflectance units) the fit shots detect, or None (unknown: ``PROBED_GLINT``).
    """

    position: Tensor
    axes: Tensor
    angle: Tensor
    normal: Tensor
    color: Tensor
    probe_lights: Tensor
    probe_cameras: Tensor
    shape: tuple[int, int]
    density: Tensor | None = None
    detect_amp: float | None = None

    def __post_init__(self) -> None:
        j = int(self.position.shape[0]) if self.position.dim() == 2 else -1
        want = {"position": (j, 2), "axes": (j, 2), "angle": (j,), "normal": (j, 3), "color": (j, 3)}
        for name, shape in want.items():
            v = getattr(self, name)
            if not isinstance(v, Tensor) or tuple(v.shape) != shape:
                raise MaterialError(f"observed flakes {name}: expected shape {shape}, found "
                                    f"{tuple(getattr(v, 'shape', ()))}")
            if not bool(torch.isfinite(v).all()):
                raise MaterialError(f"observed flakes {name}: expected finite values, found NaN/Inf")
        for name in ("probe_lights", "probe_cameras"):
            v = getattr(self, name)
            if not isinstance(v, Tensor) or v.dim() != 2 or v.shape[1] != 4 or not bool(torch.isfinite(v).all()):
                raise MaterialError(f"observed flakes {name}: expected finite (N, 4), found {tuple(getattr(v, 'shape', ()))}")
        if self.probe_lights.shape != self.probe_cameras.shape:
            raise MaterialError(f"observed flakes probes: expected lights and cameras of the same shape, found "
                                f"{tuple(self.probe_lights.shape)} and {tuple(self.probe_cameras.shape)}")
        if self.density is not None and (self.density.dim() != 2 or not bool(torch.isfinite(self.density).all())
                                         or bool((self.density < 0).any())):
            raise MaterialError(f"observed flakes density: expected a finite (gh, gw) map >= 0, found "
                                f"{tuple(self.density.shape)}")
        if bool((self.axes <= 0).any()) or bool((self.color < 0).any()) or bool((self.color > MAX_COLOR).any()):
            raise MaterialError(f"observed flakes: expected axes > 0 and colours in [0, {MAX_COLOR:g}]")
        if self.detect_amp is not None:
            if isinstance(self.detect_amp, bool) or not isinstance(self.detect_amp, (int, float)) \
                    or not (math.isfinite(self.detect_amp) and self.detect_amp > 0):
                raise MaterialError(f"observed flakes detect_amp: expected a finite number > 0 or None, "
                                    f"found {self.detect_amp!r}")
            self.detect_amp = float(self.detect_amp)
        self.shape = (int(self.shape[0]), int(self.shape[1]))

    def __len__(self) -> int:
        return int(self.position.shape[0])

    def arrays(self) -> dict[str, Tensor]:
        """name → tensor of :data:`ARRAYS` (density only when present)."""
        out = {k: getattr(self, k) for k in ARRAYS}
        if self.density is None:
            out.pop("density")
        return out



# ----------------------------------------------------------------------------- footprints


def footprints(position: Tensor, axes: Tensor, angle: Tensor, height: int, width: int):
    """Anti-aliased ellipse weights of every flake on its (2R+1)² patch.

    Returns (flake (M,), flat pixel index (M,), weight (M,)) for the candidate pixels inside the
    texture with weight > 0.
    """
    j = position.shape[0]
    dt = position.dtype
    a, b = axes[:, 0], axes[:, 1]
    r = int(math.ceil(float(a.max()))) + 1 if j else 1
    off = torch.arange(-r, r + 1, device=position.device)
    oi, oj = torch.meshgrid(off, off, indexing="ij")
    row = position[:, 0].floor().long().view(-1, 1, 1) + oi
    col = position[:, 1].floor().long().view(-1, 1, 1) + oj
    dy = row.to(dt) + 0.5 - position[:, 0].view(-1, 1, 1)
    dx = col.to(dt) + 0.5 - position[:, 1].view(-1, 1, 1)
    th = angle.view(-1, 1, 1)
    along = dx * torch.cos(th) - dy * torch.sin(th)
    across = dx * torch.sin(th) + dy * torch.cos(th)
    rho = torch.sqrt((along / a.view(-1, 1, 1)) ** 2 + (across / b.view(-1, 1, 1)) ** 2)
    wt = ((1.0 - rho) * b.view(-1, 1, 1) + 0.5).clamp(0.0, 1.0)
    inside = (row >= 0) & (row < height) & (col >= 0) & (col < width) & (wt > 0)
    flake = torch.arange(j, device=position.device).view(-1, 1, 1).expand_as(row)
    return flake[inside], (row * width + col)[inside], wt[inside]



# ----------------------------------------------------------------------------- rendering


def observed_field(obs: ObservedFlakes, height: int, width: int, normals: Tensor, glint_sigma: float) -> FlakeField:
    """The observed flakes as per-pixel maps on an H×W texture (dtype/device of ``normals`` (3, H, W)).

    Where two footprints overlap, the pixel takes the flake of the larger weight (ties: the lower index).
    """
    dt, dev = normals.dtype, normals.device
    weight = torch.zeros(height * width, dtype=dt, device=dev)
    normal = normals.reshape(3, -1).clone()
    color = torch.zeros(3, height * width, dtype=dt, device=dev)
    if len(obs):
        flake, pix, wt = footprints(obs.position.to(dev, dt), obs.axes.to(dev, dt), obs.angle.to(dev, dt), height, width)
        top = torch.zeros_like(weight).scatter_reduce(0, pix, wt, "amax")
        win = wt >= top[pix]
        owner = torch.full((height * width,), len(obs), dtype=torch.int64, device=dev).scatter_reduce(
            0, pix[win], flake[win], "amin")
        sel = owner < len(obs)
        weight[sel] = top[sel]
        normal[:, sel] = obs.normal.to(dev, dt).t()[:, owner[sel]]
        color[:, sel] = obs.color.to(dev, dt).t()[:, owner[sel]]
    shape = (height, width)
    return FlakeField(weight.view(1, *shape), normal.view(3, *shape), color.view(3, *shape), float(glint_sigma), len(obs))


def _fill_keep(model: FlakeModel, stat: FlakeField, obs: ObservedFlakes, occupied: Tensor, normals: Tensor,
               size: tuple[float, float]) -> tuple[Tensor, int]:
    """(H, W) bool: statistical-field pixels to keep, decided per hash cell (one flake each), and the
    number of statistical flakes kept."""
    h, w = occupied.shape
    c = field_cell(model)  # the field's own cells (sized for a density map's densest block)
    gw = -(-w // c)
    cell = ((torch.arange(h, device=occupied.device) // c).view(-1, 1) * gw
            + (torch.arange(w, device=occupied.device) // c).view(1, -1)).reshape(-1)
    ncell = int(cell.max()) + 1
    on = stat.weight[0].reshape(-1) > 0
    oh, ow = obs.shape
    inside = ((torch.arange(h, device=occupied.device) < oh).view(-1, 1)
              & (torch.arange(w, device=occupied.device) < ow).view(1, -1)).reshape(-1)
    drop = torch.zeros(ncell, dtype=torch.bool, device=occupied.device)
    idx = torch.nonzero(on & inside, as_tuple=True)[0]
    if idx.numel():
        # probed: some fit shot's half vector came within the glint width of the flake's normal
        rows, cols = idx // w, idx % w
        dt = normals.dtype
        x = (cols.to(dt) + 0.5) / w * size[0] - 0.5 * size[0]
        y = 0.5 * size[1] - (rows.to(dt) + 0.5) / h * size[1]
        pts = torch.stack([x, y, torch.zeros_like(x)]).unsqueeze(1)
        lights, cams = obs.probe_lights.to(normals.device, dt), obs.probe_cameras.to(normals.device, dt)
        half = shading_geometry(normals.reshape(3, -1)[:, idx].unsqueeze(1), lights, torch.ones_like(lights[:, :3]),
                                cams, points=pts).half[:, :, 0]  # (N, 3, M)
        m = stat.normal.reshape(3, -1)[:, idx].unsqueeze(0)
        g = torch.exp(-((m - half) ** 2).sum(1) / (2.0 * stat.glint_sigma**2)).amax(0)  # (M,)
        if obs.detect_amp is None:
            seen = g >= PROBED_GLINT
        else:  # the cell's flake is dropped when its brightest pixel would have been detected
            amp = stat.weight.reshape(-1)[idx] * stat.color.reshape(3, -1)[:, idx].mean(0)
            seen = amp * g >= obs.detect_amp
        bad = seen | occupied.reshape(-1)[idx]
        drop.index_fill_(0, cell[idx][bad], True)  # any bad pixel drops its cell (CUDA has no bool scatter)
        if obs.density is not None:  # patchy glitter: thin the fill cell by cell
            gh_, gw_ = obs.density.shape
            dr = (rows * gh_ // oh).clamp(max=gh_ - 1)
            dc = (cols * gw_ // ow).clamp(max=gw_ - 1)
            ratio = obs.density.to(normals.device, dt)[dr, dc]
            u = hash_uniform(cell[idx] // gw, cell[idx] % gw, model.seed, 12, dt)
            drop.index_fill_(0, cell[idx][u >= ratio], True)
    keep = on & ~drop[cell]
    return keep.view(h, w), int(torch.unique(cell[keep]).numel())


def material_flake_field(model: FlakeModel, obs: ObservedFlakes | None, height: int, width: int,
                         normals: Tensor, size: tuple[float, float]) -> FlakeField:
    """The flake field a material renders: the observed flakes where they are, the statistical field
    (seeded by ``model``) filling what no fit shot observed (see the module docstring).

    Args:
        model: the flake statistics; obs: the observed flakes (None: the statistical field alone).
        height, width: texture size; normals: (3, H, W) surface normals; size: (width, height)
            of the surface in scene units (the fit shots' half vectors).
    """
    stat = flake_field(model, height, width, normals)
    if obs is None:
        return stat
    own = observed_field(obs, height, width, normals, model.glint_sigma)
    occupied = max_filter((own.weight > 0).to(normals.dtype), 1)[0] > 0
    keep, kept = _fill_keep(model, stat, obs, occupied, normals, size)
    keep = keep.unsqueeze(0)
    use_own = own.weight > 0
    weight = torch.where(use_own, own.weight, torch.where(keep, stat.weight, torch.zeros_like(stat.weight)))
    normal = torch.where(use_own, own.normal, stat.normal)
    color = torch.where(use_own, own.color, stat.color)
    return FlakeField(weight, normal, color, float(model.glint_sigma), len(obs) + kept)


# ----------------------------------------------------------------------------- files (docs/design.md §2.3)


def observed_json(obs: ObservedFlakes) -> dict:
    """material.json's ``observed_flakes`` entry: the count, the texture shape, the detection amplitude
    (when known) and the array file names."""
    out = {"count": len(obs), "shape": list(obs.shape), "files": {k: ARRAYS[k] for k in obs.arrays()}}
    if obs.detect_amp is not None:
        out["detect_amp"] = obs.detect_amp
    return out


def save_observed(obs: ObservedFlakes, root) -> None:
    """Write the arrays of ``obs`` as .npy files (float32) into the directory ``root``."""
    for name, v in obs.arrays().items():
        np.save(Path(root) / ARRAYS[name], np.ascontiguousarray(v.detach().cpu().float().numpy()))


def load_observed(root, entry: dict | None) -> ObservedFlakes | None:
    """Read the observed flakes named by material.json's ``observed_flakes`` entry (None → None)."""
    if not entry:
        return None
    if not isinstance(entry, dict) or not isinstance(entry.get("files"), dict) or "shape" not in entry:
        raise MaterialError(f"observed_flakes: expected {{'count', 'shape', 'files'}}, found {entry!r}")
    arrays = {}
    for name, fname in entry["files"].items():
        if name not in ARRAYS:
            raise MaterialError(f"observed_flakes: expected arrays among {sorted(ARRAYS)}, found {name!r}")
        f = Path(root) / str(fname)
        if not f.is_file():
            raise MaterialError(f"{f}: expected the observed flakes' {name} array file, found nothing")
        try:
            arrays[name] = torch.from_numpy(np.load(f, allow_pickle=False).astype(np.float32))
        except (OSError, ValueError) as e:
            raise MaterialError(f"{f}: expected a numpy .npy file, found unreadable data ({e})") from None
    missing = sorted(set(ARRAYS) - {"density"} - set(arrays))
    if missing:
        raise MaterialError(f"observed_flakes: expected arrays {missing}, found them missing")
    try:
        return ObservedFlakes(shape=tuple(entry["shape"]), detect_amp=entry.get("detect_amp"), **arrays)
    except (TypeError, ValueError) as e:
        raise MaterialError(f"observed_flakes: expected (H, W) shape, found {entry.get('shape')!r} ({e})") from None
