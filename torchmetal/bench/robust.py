"""The ``robust`` section of ``torchmetal bench``: every fit option on hard captures ends with a material.

Two tables, each row a whole ``torchmetal fit`` command in a fresh process (as a user runs it):

1. **Matrix** — the zoo's flake scenes, the sharp-highlight sphere and each real capture of the shared
   data × the option sets of :data:`OPTION_SETS`: exit status, whether a complete material was written,
   wall time and its ratio to the numpy paper process (:mod:`torchmetal.bench.paper_process`) on the same
   capture, the flake-stage share of the fit and whether a flake model was kept.
2. **Flake-stage share** — every flake-free zoo scene, the sphere and uw_gray_sphere with the default
   options: the flake stage's seconds (screen, detection, statistics and both flake choices) over the
   fit's total, which must stay ≤ :data:`SHARE_TARGET`.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

from torchmetal.bench.command import timed_process, torchmetal_argv

#: option sets of the matrix: label → extra ``torchmetal fit`` arguments
OPTION_SETS: dict[str, tuple[str, ...]] = {
    "default": (),
    "normals estimate": ("--normals", "estimate"),
    "paper's model": ("--normals", "given", "--lobe", "phong"),  # the default before normals / lobe auto
    "specular maps": ("--specular", "maps"),
    "all three": ("--normals", "estimate", "--lobe", "auto", "--specular", "maps"),
    "flakes on": ("--flakes", "on"),
}
FLAKE_SCENES = ("flakes_a", "flakes_b", "flakes_orange", "flakes_half")
SPHERE = "sphere_sharp72"
REAL = ("cards_blue", "yellow_box", "uw_gray_sphere")
SHARE_TARGET = 0.10
#: the default whole command on a shared real capture (1024² × 7 phone photos at most), every choice included
REAL_DEFAULT_TARGET_S = 30.0


def flake_share(report: dict) -> float:
    """The flake stage's share of a fit: every ``flakes*`` stage time over ``total_time``."""
    t = sum(v for k, v in report.get("stage_times", {}).items() if k.split(".")[0] == "flakes")
    total = report.get("total_time") or 0.0
    return t / total if total > 0 else float("nan")


def _material_summary(mat: Path) -> dict:
    """What a user finds in the material directory: complete or not, flakes, the flake-stage share."""
    try:
        meta = json.loads((mat / "material.json").read_text())
    except (OSError, ValueError) as e:
        return {"complete": False, "why": str(e)[:120]}
    # on use: loads torch (this module imports numpy only)
    from torchmetal.material import load_material

    try:
        load_material(mat)
    except Exception as e:  # noqa: BLE001 - the bench reports any failure to load as an incomplete material
        return {"complete": False, "why": f"{type(e).__name__}: {e}"[:160]}
    rep = meta.get("fit") or {}
    return {"complete": True, "flakes": meta.get("flakes") is not None, "share": flake_share(rep),
            "fit_total_s": rep.get("total_time")}


def _paper_seconds(capture: Path, workdir: Path, env: dict, timeout: float) -> dict:
    npz = workdir / f"{capture.name}.paper.npz"
    r = timed_process([sys.executable, "-m", "torchmetal.bench.paper_process", str(capture), str(npz)], env, timeout)
    npz.unlink(missing_ok=True)
    return r


def fit_row(capture: Path, label: str, args: tuple[str, ...], workdir: Path, env: dict, timeout: float) -> dict:
    """One ``torchmetal fit CAPTURE -o MAT ARGS -q`` in a fresh process, and what it left."""
    mat = workdir / f"{capture.name}.{label.replace(' ', '_')}.material"
    shutil.rmtree(mat, ignore_errors=True)
    r = timed_process(torchmetal_argv("fit", str(capture), "-o", str(mat), "-q", *args), env, timeout)
    row = {"capture": capture.name, "options": label, **r}
    if "error" not in r:
        row.update(_material_summary(mat))
    else:
        row["complete"] = mat.exists() and (mat / "material.json").exists()
    shutil.rmtree(mat, ignore_errors=True)
    return row


def captures(workdir: Path, data_dir: Path | None, ci: bool, names: tuple[str, ...] = (*FLAKE_SCENES, SPHERE)) -> list[Path]:
    """The matrix's capture directories: zoo scenes ``names`` (written), the shared real ones."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.synth.zoo import SCENES, ci_scenes, make_case

    scenes = {s.name: s for s in (ci_scenes() if ci else SCENES.values())}
    out = [make_case(scenes[n], workdir / n).capture_dir for n in names if n in scenes]
    if data_dir is not None:
        out += [Path(data_dir) / n for n in REAL if (Path(data_dir) / n / "capture.json").is_file()]
    return out


def share_captures(workdir: Path, data_dir: Path | None, ci: bool) -> list[Path]:
    """Every flake-free zoo scene (the sphere among them) and uw_gray_sphere."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.synth.zoo import SCENES, ci_scenes, make_case

    scenes = [s for s in (ci_scenes() if ci else SCENES.values()) if s.flakes is None]
    out = [make_case(s, workdir / s.name).capture_dir for s in scenes]
    if data_dir is not None and (Path(data_dir) / "uw_gray_sphere" / "capture.json").is_file():
        out.append(Path(data_dir) / "uw_gray_sphere")
    return out


def run_section(workdir: Path, data_dir: Path | None, env: dict, timeout: float, *, ci: bool = False,
                options: tuple[str, ...] | None = None, scenes: tuple[str, ...] = (*FLAKE_SCENES, SPHERE),
                share: bool = True, say=print) -> dict:
    """Both tables (see the module docstring); ``options``: labels of :data:`OPTION_SETS` (all when None),
    ``scenes``: the zoo scenes of the matrix, ``share``: run the second table."""
    options = {k: v for k, v in OPTION_SETS.items() if options is None or k in options}
    res: dict = {"matrix": [], "share": []}
    for cap in captures(workdir, data_dir, ci, scenes):
        paper = _paper_seconds(cap, workdir, env, timeout)
        for label, args in options.items():
            row = fit_row(cap, label, args, workdir, env, timeout)
            if "wall_s" in row and "wall_s" in paper:
                row["paper_s"] = paper["wall_s"]
                row["ratio"] = row["wall_s"] / paper["wall_s"]
            res["matrix"].append(row)
            say("  " + " | ".join(_matrix_cells(row)))
    for cap in share_captures(workdir, data_dir, ci) if share else []:
        row = fit_row(cap, "default", (), workdir, env, timeout)
        res["share"].append(row)
        say(f"  {cap.name}: flake stage {_pct(row.get('share'))} of {_num(row.get('fit_total_s'))} s")
    return res


def _num(x, spec: str = ".1f") -> str:
    return "–" if not isinstance(x, (int, float)) else format(x, spec)


def _pct(x) -> str:
    return "–" if not isinstance(x, (int, float)) or x != x else f"{100 * x:.1f} %"


def _matrix_cells(r: dict) -> list[str]:
    status = "material" if r.get("complete") and "error" not in r else f"FAILED: {r.get('error', r.get('why', ''))[:80]}"
    return [r["capture"], r["options"], status, _num(r.get("wall_s")), _num(r.get("paper_s")),
            _num(r.get("ratio"), ".2f"), _pct(r.get("share")), {True: "yes", False: "no"}.get(r.get("flakes"), "–")]


def real_default_rows(matrix: list[dict]) -> list[str]:
    """The default command's wall time on each shared real capture against :data:`REAL_DEFAULT_TARGET_S`
    (markdown lines; none without a real capture in the matrix)."""
    rows = [r for r in matrix if r["capture"] in REAL and r["options"] == "default"]
    if not rows:
        return []
    out = [f"Default whole command on the shared real captures (target ≤ {REAL_DEFAULT_TARGET_S:.0f} s):", "",
           "| capture | wall s | ≤ target |", "|---|---|---|"]
    for r in rows:
        w = r.get("wall_s")
        good = isinstance(w, (int, float)) and w <= REAL_DEFAULT_TARGET_S and "error" not in r
        out.append(f"| {r['capture']} | {_num(w)} | {'yes' if good else 'NO'} |")
    return out + [""]


def markdown(res: dict) -> str:
    rows = ["| capture | options | result | wall s | numpy paper s | ratio | flake stage | flake model |",
            "|---|---|---|---|---|---|---|---|"]
    rows += ["| " + " | ".join(_matrix_cells(r)) + " |" for r in res["matrix"]]
    ok = sum(bool(r.get("complete")) and "error" not in r for r in res["matrix"])
    rows += ["", f"{ok} of {len(res['matrix'])} runs wrote a complete material.", ""]
    rows += real_default_rows(res["matrix"])
    rows += [f"Flake-stage share of the default fit on flake-free captures (target ≤ {SHARE_TARGET:.0%}):", "",
             "| capture | fit s | flake stage | ≤ target |", "|---|---|---|---|"]
    for r in res["share"]:
        s = r.get("share")
        good = isinstance(s, float) and s == s and s <= SHARE_TARGET
        rows.append(f"| {r['capture']} | {_num(r.get('fit_total_s'), '.2f')} | {_pct(s)} | {'yes' if good else 'NO'} |")
    return "\n".join(rows)
