"""The fitted material and its directory on disk (docs/design.md §2.3).

```
material/
  material.json          format "torchmetal-material", version 1
  texture.npy            (H, W, 3) float32 linear diffuse texture d(p)
  normals.npy            (H, W, 3) float32, only when not flat
  specular_labels.npy    (H, W) int32, only with clustered specular
  gloss_s.npy, gloss_alpha.npy   (H, W, 3) float32 gloss maps, only with specular="maps"
  flakes_*.npy           observed flakes (torchmetal.flakes.model.observed), named in material.json
  flakes_density_map.npy, flakes_color_map.npy   (gh, gw) / (gh, gw, 3) float32 flake-density map and
                         per-block colour means (torchmetal.flakes.estimate.density_map), named in material.json
  flakes_area_map.npy    (gh, gw) float32 per-block flake log-area offsets, named in material.json
  normals_interval_deg.npy   (H, W) float32 90 % radius of the estimated normals in degrees (``torchmetal
                         intervals``), named in the report at fit.uncertainty.leave_out.normals.file
  disagreement.png       the fit report's disagreement map (``torchmetal fit``), named in the report at
                         fit.disagreement.file
  renderer.onnx          when exported
```
Writes are atomic: everything goes to a temporary sibling directory that replaces the target in
one rename, so an interrupted save never leaves a half-written material.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchmetal.errors import MaterialError
from torchmetal.flakes.model import FlakeModel
from torchmetal.flakes.model.observed import ObservedFlakes, load_observed, observed_json, save_observed
from torchmetal.io.capture_save import replace_dir
from torchmetal.lobes import LOBES

FORMAT = "torchmetal-material"
VERSION = 1


@dataclass
class Material:
    """Everything needed to render the sample for any light and camera.

    Attributes:
        texture: (3, H, W) linear diffuse texture.
        s, alpha: (3,) global specular strength and exponent (the paper's model). With clustered
            specular they hold the area-weighted mean, and ``cluster_s``/``cluster_alpha`` (K, 3)
            with ``spec_labels`` (H, W) int64 give the per-pixel terms.
        size: (width, height) of the surface in scene units.
        normals: (3, H, W) unit normals, or None for flat (0, 0, 1).
        flakes: the flake model, or None when the sample has no flakes.
        report: the fit report (per-stage times, iterations, errors, what was skipped).
        lobe: the specular lobe of ``s``/``alpha``: "phong" (docs/design.md §2.2, the default), "blinn" or
            "ggx" (:mod:`torchmetal.lobes`); saved as ``"lobe"`` in material.json (absent = phong).
        normals_interval: (H, W) float32 per-pixel 90 % radius in degrees of the estimated normals, from refits
            with one shot left out (``torchmetal intervals``, :mod:`torchmetal.plan.intervals`), or None. Carried
            here so that a re-saved material keeps the file its report names (:data:`NORMALS_INTERVAL_FILE`).
        disagreement_png: the bytes of the fit report's disagreement map (:data:`DISAGREEMENT_FILE`,
            :mod:`torchmetal.report.fit_maps`), as read from a material directory, or None; carried for the same
            reason (the report's ``disagreement`` entry names the file).
    """

    texture: Tensor
    s: Tensor
    alpha: Tensor
    size: tuple[float, float]
    normals: Tensor | None = None
    spec_labels: Tensor | None = None
    cluster_s: Tensor | None = None
    cluster_alpha: Tensor | None = None
    flakes: FlakeModel | None = None
    report: dict = field(default_factory=dict)
    lobe: str = "phong"
    observed_flakes: "ObservedFlakes | None" = None  # the sample's own flakes (torchmetal.flakes.model.observed)
    gloss_s: Tensor | None = None  # (3, H, W) gloss maps (torchmetal.fit.gloss); s, alpha hold their means
    gloss_alpha: Tensor | None = None
    normals_interval: Tensor | None = None  # (H, W) degrees, torchmetal intervals' normals radius map
    disagreement_png: bytes | None = None  # the disagreement map's PNG file, verbatim

    def __post_init__(self) -> None:
        if self.lobe not in LOBES:
            raise MaterialError(f"lobe: expected one of {list(LOBES)}, found {self.lobe!r}")
        t = self.texture
        if not isinstance(t, Tensor) or t.dim() != 3 or t.shape[0] != 3:
            found = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise MaterialError(f"texture: expected shape (3, H, W), found {found}")
        for name in ("s", "alpha"):
            v = getattr(self, name)
            if not isinstance(v, Tensor) or tuple(v.shape) != (3,):
                raise MaterialError(f"{name}: expected shape (3,), found {tuple(getattr(v, 'shape', ()))}")
        if self.normals is not None and tuple(self.normals.shape) != tuple(t.shape):
            raise MaterialError(f"normals: expected shape {tuple(t.shape)}, found {tuple(self.normals.shape)}")
        clustered = [x is not None for x in (self.spec_labels, self.cluster_s, self.cluster_alpha)]
        if any(clustered) and not all(clustered):
            raise MaterialError("clustered specular: expected spec_labels, cluster_s and cluster_alpha together")
        if self.spec_labels is not None:
            if tuple(self.spec_labels.shape) != tuple(t.shape[1:]):
                raise MaterialError(f"spec_labels: expected shape {tuple(t.shape[1:])}, found {tuple(self.spec_labels.shape)}")
            k = self.cluster_s.shape[0]
            if self.cluster_s.shape != (k, 3) or self.cluster_alpha.shape != (k, 3):
                raise MaterialError(f"cluster_s/cluster_alpha: expected (K, 3), found {tuple(self.cluster_s.shape)}, {tuple(self.cluster_alpha.shape)}")
        self._check_gloss()
        if self.normals_interval is not None and tuple(self.normals_interval.shape) != tuple(t.shape[1:]):
            raise MaterialError(f"normals_interval: expected shape {tuple(t.shape[1:])}, found {tuple(self.normals_interval.shape)}")
        if self.disagreement_png is not None and not (isinstance(self.disagreement_png, bytes)
                                                      and self.disagreement_png.startswith(PNG_MAGIC)):
            raise MaterialError(f"disagreement_png: expected the bytes of a PNG file, found {repr(self.disagreement_png)[:24]}")
        if not (all(math.isfinite(v) and v > 0 for v in self.size) and len(self.size) == 2):
            raise MaterialError(f"size: expected two positive numbers (width, height), found {self.size!r}")

    def _check_gloss(self) -> None:
        if (self.gloss_s is None) != (self.gloss_alpha is None):
            raise MaterialError("gloss maps: expected gloss_s and gloss_alpha together, found only one")
        if self.gloss_s is None:
            return
        if self.spec_labels is not None:
            raise MaterialError("gloss maps: expected either gloss maps or clustered specular, found both")
        for name in ("gloss_s", "gloss_alpha"):
            x = getattr(self, name)
            if not isinstance(x, Tensor) or tuple(x.shape) != tuple(self.texture.shape):
                found = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
                raise MaterialError(f"{name}: expected shape {tuple(self.texture.shape)}, found {found}")
            if not bool(torch.isfinite(x).all()):
                raise MaterialError(f"{name}: expected finite values, found NaN/Inf")
        if bool((self.gloss_s < 0).any()) or bool((self.gloss_alpha <= 0).any()):
            raise MaterialError(f"gloss maps: expected s >= 0 and alpha > 0, found min s {float(self.gloss_s.min()):g}, "
                                f"min alpha {float(self.gloss_alpha.min()):g}")

    @property
    def height(self) -> int:
        return int(self.texture.shape[1])

    @property
    def width(self) -> int:
        return int(self.texture.shape[2])

    @property
    def clustered(self) -> bool:
        return self.spec_labels is not None

    def flat_normals(self) -> Tensor:
        """(3, H, W) normals, (0, 0, 1) when the material is flat."""
        if self.normals is not None:
            return self.normals
        n = torch.zeros_like(self.texture)
        n[2] = 1.0
        return n

    def specular_maps(self) -> tuple[Tensor, Tensor]:
        """s and α as (3,) globals, or (3, H, W) maps for clustered specular and gloss maps."""
        if self.gloss_s is not None:
            return self.gloss_s, self.gloss_alpha
        if self.spec_labels is None:
            return self.s, self.alpha
        lab = self.spec_labels.long()
        return self.cluster_s[lab].permute(2, 0, 1), self.cluster_alpha[lab].permute(2, 0, 1)

    def to(self, device: torch.device | str) -> "Material":
        move = lambda x: None if x is None else x.to(device)  # noqa: E731
        return Material(
            move(self.texture), move(self.s), move(self.alpha), self.size, move(self.normals),
            move(self.spec_labels), move(self.cluster_s), move(self.cluster_alpha), self.flakes, dict(self.report),
            lobe=self.lobe, observed_flakes=self.observed_flakes, gloss_s=move(self.gloss_s), gloss_alpha=move(self.gloss_alpha),
            normals_interval=move(self.normals_interval), disagreement_png=self.disagreement_png,
        )


def _to_list(x: Tensor) -> list:
    return x.detach().cpu().double().tolist()


def json_finite(x):
    """JSON-safe: non-finite floats become strings ("inf", "nan") so ``json.dumps(allow_nan=False)`` never
    fails (a decision's held-out PSNR is inf for a perfect prediction); dicts, lists, tuples and tensors
    recursively."""
    if isinstance(x, float):
        return x if math.isfinite(x) else str(x)
    if isinstance(x, dict):
        return {str(k): json_finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_finite(v) for v in x]
    if isinstance(x, torch.Tensor):
        return json_finite(x.tolist())
    return x


def material_to_json(m: Material, files: set[str] | None = None) -> dict:
    return {
        "format": FORMAT,
        "version": VERSION,
        "surface": {"width": float(m.size[0]), "height": float(m.size[1])},
        "resolution": [m.height, m.width],
        "texture": "texture.npy",
        "normals": "normals.npy" if m.normals is not None else None,
        "lobe": m.lobe,
        "phong": {
            "s": _to_list(m.s),
            "alpha": _to_list(m.alpha),
            "clusters": None
            if m.spec_labels is None
            else {"labels": "specular_labels.npy", "s": _to_list(m.cluster_s), "alpha": _to_list(m.cluster_alpha)},
            "maps": None if m.gloss_s is None else {"s": "gloss_s.npy", "alpha": "gloss_alpha.npy"},
        },
        "flakes": _flakes_json(m.flakes),
        "observed_flakes": None if m.observed_flakes is None else observed_json(m.observed_flakes),
        "fit": json_finite(_report_naming_files(m, files)),
    }


NORMALS_INTERVAL_FILE = "normals_interval_deg.npy"
DISAGREEMENT_FILE = "disagreement.png"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# the report entries that name a file of the directory: where, and the file's name
_REPORT_FILES = ((("uncertainty", "leave_out", "normals"), NORMALS_INTERVAL_FILE), (("disagreement",), DISAGREEMENT_FILE))


def _report_naming_files(m: Material, files: set[str] | None = None) -> dict:
    """``m.report`` as saved: each entry of :data:`_REPORT_FILES` names its file exactly when the file is written
    (``files``, the names in the directory; default those the Material carries: ``normals_interval``,
    ``disagreement_png``), so the report never names a file the directory lacks (a material loaded from a
    directory that lost it: the name goes) nor holds one it does not name."""
    if files is None:
        files = {name for name, x in ((NORMALS_INTERVAL_FILE, m.normals_interval), (DISAGREEMENT_FILE, m.disagreement_png))
                 if x is not None}
    report = m.report
    for path, name in _REPORT_FILES:
        want = name if name in files else None
        if _named_file(report, path) == want:
            continue
        if report is m.report:
            report = json.loads(json.dumps(json_finite(m.report)))  # a copy: the caller's report is not changed
        node = report
        for key in path:
            if not isinstance(node.get(key), dict):
                node[key] = {}
            node = node[key]
        if want is None:
            node.pop("file", None)
        else:
            node["file"] = want
    return report


def _named_file(report: dict, path: tuple[str, ...]) -> str | None:
    """The file the report's entry at ``path`` names (None: none)."""
    entry = report
    for key in path:
        entry = entry.get(key) if isinstance(entry, dict) else None
    return entry.get("file") if isinstance(entry, dict) else None


FLAKE_MAP_FILES = {"density_map": "flakes_density_map.npy", "color_map": "flakes_color_map.npy",
                   "area_map": "flakes_area_map.npy"}


def _flakes_json(f: FlakeModel | None) -> dict | None:
    """material.json's ``flakes``: the statistics, plus ``maps`` naming the array files of the maps it has."""
    if f is None:
        return None
    d = f.to_dict()
    if "extra" in d:  # the fit's report on the statistics: a standard error not computed is NaN
        d["extra"] = json_finite(d["extra"])
    maps = {k: v for k, v in FLAKE_MAP_FILES.items() if getattr(f, k) is not None}
    if maps:
        d["maps"] = maps
    return d


def _load_flakes(root: Path, entry: dict | None) -> FlakeModel | None:
    """The FlakeModel of material.json's ``flakes`` entry, with its map arrays (see :func:`_flakes_json`)."""
    if not entry:
        return None
    d = dict(entry)
    maps = d.pop("maps", None) or {}
    if not isinstance(maps, dict) or not set(maps) <= set(FLAKE_MAP_FILES):
        raise MaterialError(f"flakes.maps: expected a dict with keys among {sorted(FLAKE_MAP_FILES)}, found {maps!r}")
    for key, name in maps.items():
        d[key] = _load_array(root, str(name), "(gh, gw, 3)" if key == "color_map" else "(gh, gw)")
    return FlakeModel.from_dict(d)


def _hwc(x: Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().cpu().float().permute(1, 2, 0).numpy())


def save_material(m: Material, path: str | os.PathLike, *, extra_files: dict[str, Path] | None = None) -> Path:
    """Write ``m`` to the material directory ``path`` atomically; returns the path.

    ``extra_files`` maps names in the directory to files to copy in (e.g. ``renderer.onnx``).
    An existing ``renderer.onnx`` in the target is kept unless replaced.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        np.save(tmp / "texture.npy", _hwc(m.texture))
        if m.normals is not None:
            np.save(tmp / "normals.npy", _hwc(m.normals))
        if m.spec_labels is not None:
            np.save(tmp / "specular_labels.npy", m.spec_labels.detach().cpu().numpy().astype(np.int32))
        if m.gloss_s is not None:
            np.save(tmp / "gloss_s.npy", _hwc(m.gloss_s))
            np.save(tmp / "gloss_alpha.npy", _hwc(m.gloss_alpha))
        if m.observed_flakes is not None:
            save_observed(m.observed_flakes, tmp)
        for key, name in FLAKE_MAP_FILES.items():
            arr = None if m.flakes is None else getattr(m.flakes, key)
            if arr is not None:
                np.save(tmp / name, np.ascontiguousarray(arr.detach().cpu().float().numpy()))
        if m.normals_interval is not None:
            np.save(tmp / NORMALS_INTERVAL_FILE, np.ascontiguousarray(m.normals_interval.detach().cpu().float().numpy()))
        if m.disagreement_png is not None:
            (tmp / DISAGREEMENT_FILE).write_bytes(m.disagreement_png)
        keep = path / "renderer.onnx"
        if keep.is_file() and not (extra_files and "renderer.onnx" in extra_files):
            shutil.copy2(keep, tmp / "renderer.onnx")
        for name, src in (extra_files or {}).items():
            shutil.copy2(src, tmp / name)
        # last: the report names the files the directory has (torchmetal fit's map comes in extra_files)
        files = {name for name in (NORMALS_INTERVAL_FILE, DISAGREEMENT_FILE) if (tmp / name).is_file()}
        (tmp / "material.json").write_text(json.dumps(material_to_json(m, files), indent=2, allow_nan=False))
        replace_dir(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def _load_array(root: Path, name: str, shape_hint: str) -> np.ndarray:
    f = root / name
    if not f.is_file():
        raise MaterialError(f"{f}: expected a {shape_hint} array file, found nothing")
    try:
        return np.load(f, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise MaterialError(f"{f}: expected a numpy .npy file, found unreadable data ({e})") from None


def _load_map(root: Path, name: str, shape: torch.Size) -> Tensor:
    """(H, W, 3) gloss map file → (3, H, W) float32."""
    a = _load_array(root, name, "(H, W, 3)")
    if a.shape != (shape[1], shape[2], 3):
        raise MaterialError(f"{root / name}: expected shape {(shape[1], shape[2], 3)}, found {a.shape}")
    return torch.from_numpy(a.astype(np.float32)).permute(2, 0, 1).contiguous()


def load_material(path: str | os.PathLike) -> Material:
    """Read a material directory written by :func:`save_material`."""
    root = Path(path)
    meta_file = root / "material.json"
    if not meta_file.is_file():
        raise MaterialError(f"{root}: expected a material directory with material.json, found none")
    try:
        meta = json.loads(meta_file.read_text())
    except json.JSONDecodeError as e:
        raise MaterialError(f"{meta_file}: expected JSON, found a syntax error at line {e.lineno} column {e.colno}: {e.msg}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise MaterialError(f"{meta_file}: expected format {FORMAT!r}, found {meta.get('format') if isinstance(meta, dict) else meta!r}")
    if meta.get("version") != VERSION:
        raise MaterialError(f"{meta_file}: expected version {VERSION}, found {meta.get('version')!r}")
    try:
        tex = _load_array(root, meta["texture"], "(H, W, 3)")
        if tex.ndim != 3 or tex.shape[2] != 3:
            raise MaterialError(f"{root / meta['texture']}: expected shape (H, W, 3), found {tex.shape}")
        texture = torch.from_numpy(tex.astype(np.float32)).permute(2, 0, 1).contiguous()
        normals = None
        if meta.get("normals"):
            normals = torch.from_numpy(_load_array(root, meta["normals"], "(H, W, 3)").astype(np.float32)).permute(2, 0, 1).contiguous()
        ph = meta["phong"]
        s = torch.tensor(ph["s"], dtype=torch.float32)
        alpha = torch.tensor(ph["alpha"], dtype=torch.float32)
        labels = cs = ca = None
        if ph.get("clusters"):
            cl = ph["clusters"]
            labels = torch.from_numpy(_load_array(root, cl["labels"], "(H, W)").astype(np.int64))
            cs = torch.tensor(cl["s"], dtype=torch.float32)
            ca = torch.tensor(cl["alpha"], dtype=torch.float32)
        gs = ga = None
        if ph.get("maps"):
            gs, ga = (_load_map(root, ph["maps"][k], texture.shape) for k in ("s", "alpha"))
        flakes = _load_flakes(root, meta.get("flakes"))
        observed = load_observed(root, meta.get("observed_flakes")) if flakes is not None else None
        size = (float(meta["surface"]["width"]), float(meta["surface"]["height"]))
        lobe = meta.get("lobe", "phong")  # absent: a material from before the lobe choice
        interval = _load_interval(root, meta.get("fit") or {}, texture.shape[1:])
        disagreement = _load_disagreement(root, meta.get("fit") or {})
    except KeyError as e:
        raise MaterialError(f"{meta_file}: expected key {e.args[0]!r}, found it missing") from None
    except (TypeError, ValueError) as e:
        raise MaterialError(f"{meta_file}: expected numeric parameters, found {e}") from None
    for name, x in (("texture", texture), ("s", s), ("alpha", alpha)):
        if not bool(torch.isfinite(x).all()):
            raise MaterialError(f"{root}: expected finite {name}, found NaN/Inf")
    return Material(texture, s, alpha, size, normals, labels, cs, ca, flakes, meta.get("fit") or {}, lobe=lobe,
                    observed_flakes=observed, gloss_s=gs, gloss_alpha=ga, normals_interval=interval,
                    disagreement_png=disagreement)


def _load_interval(root: Path, report: dict, hw: torch.Size) -> Tensor | None:
    """The (H, W) normals radius map the report names, or None: none named, or named but missing (a material
    re-saved before the map was carried dropped it; its next save drops the name, :func:`_report_naming_files`)."""
    name = _named_file(report, _REPORT_FILES[0][0])
    if name is None or not (root / str(name)).is_file():
        return None
    a = _load_array(root, str(name), "(H, W)")
    if a.shape != tuple(hw):
        raise MaterialError(f"{root / name}: expected shape {tuple(hw)}, found {a.shape}")
    return torch.from_numpy(a.astype(np.float32))


def _load_disagreement(root: Path, report: dict) -> bytes | None:
    """The PNG bytes of the disagreement map the report names, or None: none named, or named but missing (a
    material re-saved before the map was carried dropped it; its next save drops the name)."""
    name = _named_file(report, _REPORT_FILES[1][0])
    f = root / str(name) if name is not None else None
    if f is None or not f.is_file():
        return None
    data = f.read_bytes()
    if not data.startswith(PNG_MAGIC):
        raise MaterialError(f"{f}: expected a PNG file, found {data[:8]!r}")
    return data
