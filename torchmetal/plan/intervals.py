"""``torchmetal intervals MATERIAL CAPTURE``: leave-out intervals of a fitted material, written into its report.

The fit's own intervals (s, α, the texture: curvature, :mod:`torchmetal.fit.uncertainty`) are in every material's
report (``uncertainty``). The flake statistics and estimated normals have no curvature to read: their 90 %
intervals come from refits with one shot left out (the jackknife of :mod:`torchmetal.plan.leave_out`), N fits for
N shots — too slow for every fit, so they are an opt-in a user runs after one (issue 43, item 1).

Each refit is the material's own fit on the capture less one shot, with the choices the fit made fixed (the
registration, clipping, normals, light, lobe, weights, specular structure and scheme its report records;
:func:`refit_options`), the flake stage on (``flakes="on"``: the statistics are wanted whenever detections exceed
noise) and no observed flakes (they do not change the statistics). The interval is centred on the material's own
values; a refit that finds no flake model is counted and left out (:func:`~torchmetal.plan.leave_out.flake_jackknife`).

What is written (docs/design.md §2.3: the report is free-form, nothing required changes): material.json's
``fit.uncertainty.leave_out`` = {"method", "level", "refits", "options", "seconds", "flakes": {statistic: {"value",
"low", "high", "std", "scale", "refits"}, "failed_refits"}, "normals": {"median_radius_deg", "p90_radius_deg",
"file"}} (each of the last two only where the material has it), and for normals the per-pixel 90 % radius in
degrees, ``normals_interval_deg.npy`` (H, W) float32 — at least, where the material's normal is the flat test's
(0, 0, 1), the tilt that test could not reject on this capture (:func:`flat_floor`). Every other byte of
material.json stays as the fit wrote it.
The report names that file exactly when it is in the directory: a run without normals removes an earlier run's
file, and :func:`~torchmetal.material.save_material` carries it (``Material.normals_interval``) through a reload
and re-save, or drops the name where the map is gone.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from torchmetal.errors import InputError
from torchmetal.material import NORMALS_INTERVAL_FILE as NORMALS_FILE  # the material directory's name for the map
from torchmetal.plan.leave_out import LEVEL, flake_jackknife, normals_jackknife

REPORT_KEY = "leave_out"  # under the report's "uncertainty"
ESTIMATED_NORMALS = ("estimate", "relief")  # the normals modes that estimate normals from the photos
MIN_SHOTS = 4  # three shots left in every refit


def refit_options(report: dict, material) -> dict:
    """``fit_material`` keywords that redo the material's fit with its choices fixed: each choice the report records
    as chosen (or as given by the caller), the lobe, the weights (noise where the fit had a noise model), the
    specular structure, the scheme; flakes on where the material has them (else off), observed flakes off."""
    from torchmetal.config import ChoiceOptions, FitConfig, SolverOptions

    allowed = {f.name: f.metadata["choices"] for cls in (ChoiceOptions, SolverOptions) for f in dataclasses.fields(cls)}
    opts: dict = {}

    def put(name: str, value) -> None:
        if value is not None and value != "auto" and value in (allowed.get(name) or ()):
            opts[name] = value

    for name, key in (("registration", "registered"), ("clipping", "clipping"), ("normals", "normals"), ("light", "light")):
        entry = report.get(key) or {}
        put(name, entry.get("chosen") or entry.get("mode"))
    put("lobe", material.lobe)
    if "noise" in report:
        put("weights", "noise" if report["noise"] else "uniform")
    put("specular", report.get("specular"))
    put("scheme", report.get("scheme"))
    opts["flakes"] = "on" if material.flakes is not None else "off"
    opts["observed_flakes"] = "off"
    if material.flakes is not None:
        opts["seed"] = int(material.flakes.seed)
    FitConfig.of(None, **opts)  # refuses anything the config does not take
    return opts


def default_refit(options: dict) -> Callable:
    """A capture → Material function: :func:`~torchmetal.pipeline.fit_material` with ``options``."""
    from torchmetal.pipeline import fit_material

    return lambda capture: fit_material(capture, **options).material


def leave_out_intervals(material_dir: str | Path, capture_dir: str | Path, *, level: float = LEVEL,
                        refit: Callable | None = None, log: Callable[[str], None] | None = None) -> dict:
    """Refit the material at ``material_dir`` once per shot of the capture at ``capture_dir`` left out, and write the
    flake statistics' and estimated normals' intervals into the material's report (module docstring). ``refit``:
    capture → Material (default: :func:`default_refit` of :func:`refit_options`); ``log``: called with a line per
    refit. Returns the report entry written. Raises :class:`~torchmetal.errors.InputError` when the capture is not
    the material's (another size), has fewer than :data:`MIN_SHOTS` shots, or the material has neither flakes nor
    estimated normals."""
    import torch

    from torchmetal.io.capture import load_capture
    from torchmetal.material import load_material

    material_dir, capture_dir = Path(material_dir), Path(capture_dir)
    if not (material_dir / "material.json").is_file():
        raise InputError(f"intervals: expected a material directory (material.json), found {material_dir}")
    if not (capture_dir / "capture.json").is_file():
        raise InputError(f"intervals: expected a capture directory (capture.json), found {capture_dir}")
    material = load_material(material_dir)
    capture = load_capture(capture_dir)
    if (capture.height, capture.width) != (material.height, material.width):
        raise InputError(f"intervals: the capture is {capture.height}x{capture.width} pixels and the material "
                         f"{material.height}x{material.width}: not the capture it was fitted to")
    n = capture.num_shots
    if n < MIN_SHOTS:
        raise InputError(f"intervals: expected at least {MIN_SHOTS} shots (3 left in each refit), found {n}")
    report = material.report or {}
    chosen = (report.get("normals") or {}).get("chosen")
    want_normals = chosen in ESTIMATED_NORMALS and material.normals is not None
    want_flakes = material.flakes is not None
    if not (want_flakes or want_normals):
        raise InputError(f"intervals: {material_dir} has no flake model and no estimated normals (normals: {chosen}): "
                         "nothing to refit; its s, alpha and texture intervals are in its report (uncertainty) already")
    options = refit_options(report, material)
    refit = refit or default_refit(options)
    t0 = time.perf_counter()
    models, normals = [], []
    for i in range(n):
        t = time.perf_counter()
        m = refit(capture.subset([j for j in range(n) if j != i]))
        models.append(m.flakes)
        if want_normals:
            normals.append(m.flat_normals().detach().double().cpu())
        if log is not None:
            log(f"refit {i + 1}/{n} (shot {i} left out): {time.perf_counter() - t:.1f} s")
    entry: dict = {"method": "jackknife over shots: the material's fit redone with one shot left out, its choices fixed",
                   "level": level, "refits": n, "options": options, "seconds": round(time.perf_counter() - t0, 2)}
    radius = None
    if want_flakes:
        fl = flake_jackknife(material.flakes, models, level=level)
        entry["flakes"] = {k: v for k, v in fl.items() if k != "level"}
    if want_normals:
        inside = capture.mask.bool().reshape(capture.height, capture.width).cpu()
        full = material.normals.detach().double().cpu()
        nj = normals_jackknife(full, torch.stack(normals), inside, level=level,
                               flat_floor_deg=flat_floor(capture, full, report, material))
        radius = nj["radius_deg"].float().numpy()
        entry["normals"] = {"median_radius_deg": nj["median_radius_deg"], "p90_radius_deg": nj["p90_radius_deg"],
                            "file": NORMALS_FILE}
    write_entry(material_dir, entry, radius)
    return entry


def flat_floor(capture, normals, report: dict, material):
    """(H, W) float64 degrees: the tilt the material's flat test could not reject where it set a normal flat
    (:func:`~torchmetal.normals.flat.unrejected_tilt_deg` on ``capture``), with the specular terms the estimate
    ran it with (the report's ``normals`` "s", "alpha"; a material fitted before they were recorded: its own s, α)."""
    import torch

    from torchmetal.normals.flat import unrejected_tilt_deg

    entry = report.get("normals") or {}
    s, alpha = entry.get("s"), entry.get("alpha")
    if not (isinstance(s, list) and isinstance(alpha, list) and len(s) == len(alpha) == 3):
        s, alpha = material.s.reshape(-1)[:3].tolist(), material.alpha.reshape(-1)[:3].tolist()
    dt = capture.images.dtype
    return unrejected_tilt_deg(capture, normals.to(dt), torch.tensor(s, dtype=dt), torch.tensor(alpha, dtype=dt)).cpu()


def write_entry(material_dir: Path, entry: dict, radius=None) -> None:
    """Put ``entry`` at material.json's ``fit.uncertainty.leave_out`` (and ``radius`` (H, W) into
    :data:`NORMALS_FILE`, which ``entry["normals"]["file"]`` names), each file replaced atomically; the rest of
    material.json is written back as it was. Without ``radius`` an earlier run's map is removed: the new entry does
    not name it, and a file the report does not name would be carried by nothing (load_material reads what it names)."""
    import numpy as np

    from torchmetal.material import json_finite

    meta_file = material_dir / "material.json"
    doc = json.loads(meta_file.read_text())
    fit = doc.setdefault("fit", {})
    if not isinstance(fit.get("uncertainty"), dict):
        fit["uncertainty"] = {}
    fit["uncertainty"][REPORT_KEY] = json_finite(entry)
    if (radius is not None) != bool((entry.get("normals") or {}).get("file")):
        raise ValueError("write_entry: the entry names the normals file exactly when a radius map is given")
    if radius is not None:
        _atomic(material_dir / NORMALS_FILE, lambda f: np.save(f, np.ascontiguousarray(radius, dtype=np.float32)))
    text = json.dumps(doc, indent=2, allow_nan=False)  # as save_material writes it
    _atomic(meta_file, lambda f: f.write(text.encode()))
    if radius is None:  # after material.json: it no longer names the map
        (material_dir / NORMALS_FILE).unlink(missing_ok=True)


def _atomic(path: Path, write: Callable) -> None:
    """Write ``path`` through a temporary file beside it and a rename: never half-written."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _num(v: float) -> str:
    return f"{v:.3g}" if isinstance(v, (int, float)) and math.isfinite(v) else "n/a"


def describe(entry: dict) -> str:
    """The verb's printout: the flake density's interval (the other statistics: the report) and the normals' radius,
    one line each: ``flake density 0.0041 [0.0035, 0.0049] (90 %, 7 leave-one-out refits)``."""
    pct = f"{100 * entry['level']:.0f} %"
    n = entry["refits"]
    lines = []
    fl = entry.get("flakes")
    if fl:
        d = fl["density"]
        failed = fl.get("failed_refits", 0)
        note = f", {failed} without flakes" if failed else ""
        if math.isfinite(d["low"]) and math.isfinite(d["high"]):
            lines.append(f"flake density {_num(d['value'])} [{_num(d['low'])}, {_num(d['high'])}] ({pct}, {n} leave-one-out "
                         f"refits{note})")
        else:
            lines.append(f"flake density {_num(d['value'])}: no interval ({n - failed} of {n} leave-one-out refits found "
                         "flakes, 3 needed)")
    nr = entry.get("normals")
    if nr:
        lines.append(f"normals {pct} radius median {_num(nr['median_radius_deg'])} deg, p90 {_num(nr['p90_radius_deg'])} deg "
                     f"({n} leave-one-out refits; per pixel: {nr['file']})")
    return "\n".join(lines)
