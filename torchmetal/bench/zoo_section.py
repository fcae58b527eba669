"""The ``zoo`` section of ``torchmetal bench``: the scene zoo (:mod:`torchmetal.synth.zoo`) fitted
with the default pipeline and the paper's scheme, scored against the noise-free truth
(:mod:`torchmetal.bench.zoo`). Plan helpers, the per-scene job list and the Markdown table.
"""

from __future__ import annotations

import math

from torchmetal.bench.zoo import METHODS

VERDICT_DB = 0.2  # "default ≥ paper − 0.2 dB" (coat PSNR)


def zoo_scene_names(names: tuple[str, ...] | None) -> list[str]:
    """The scenes a plan runs: ``names`` (in that order) or every scene of the zoo."""
    # on use: loads torch (this module imports numpy only)
    from torchmetal.synth.zoo import SCENES

    return list(SCENES) if names is None else [n for n in names if n in SCENES]


def zoo_jobs(ci: bool, names: list[str]) -> list[tuple[str, dict]]:
    """One job per scene, each fitting :data:`torchmetal.bench.zoo.METHODS`."""
    return [("zoo", {"scene": n, "ci": bool(ci), "methods": METHODS}) for n in names]


def _f(x) -> float:
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")


def _db(x) -> str:
    v = _f(x)
    return "–" if math.isnan(v) else ("∞" if math.isinf(v) else f"{v:.2f}")


def _coat_cell(row: dict) -> str:
    """Coat PSNR, and the as-rendered PSNR (sparkles included) where it differs."""
    coat, full = _f(row.get("psnr_coat")), _f(row.get("psnr"))
    if math.isfinite(coat) and math.isfinite(full) and abs(coat - full) >= 0.005:
        return f"{_db(coat)} (as rendered {_db(full)})"
    return _db(coat)


def _oracle_cell(r: dict) -> str:
    """The oracle's PSNR; on flake scenes also the truth with its flakes redrawn (the yardstick of 'as rendered')."""
    if "oracle_sparkles" not in r:
        return _db(r.get("oracle"))
    return f"{_db(r.get('oracle'))} (flakes redrawn {_db(r['oracle_sparkles'])})"


def _err_cell(row: dict) -> str:
    if "s_err" not in row:
        return "–"
    return f"{_f(row['s_err']):.1%} / {_f(row['alpha_err']):.1%}"


def _flake_cell(row: dict, truth: dict) -> str:
    true_flakes = "density" in (truth or {})
    if row.get("flake_model"):
        if "density_err" in row:
            ratio = f", colour ×{_f(row['color_ratio']):.2f}" if "color_ratio" in row else ""
            ratio += f", sparkles ×{_f(row['sparkle_ratio']):.2f}" if "sparkle_ratio" in row else ""
            return (f"yes (density {_f(row['density_err']):.0%}, area {_f(row['area_err']):.0%}, "
                    f"tilt {_f(row['tilt_err']):.0%}{ratio})")
        return "yes (FALSE: no flakes in the truth)"
    return "no" + (" (MISSED)" if true_flakes else "")


def _stages_cell(row: dict) -> str:
    st = row.get("stage_times") or {}
    parts = [f"{k.removeprefix('phong.')} {_f(v):.2f}" for k, v in st.items()
             if k.startswith("phong.") or k == "flakes"]
    return ", ".join(parts) or "–"


def _skip_share_cell(row: dict) -> str:
    """The flake stage's seconds over the Phong fit's (target: ≤ 10 % where the stage is skipped)."""
    st = row.get("stage_times") or {}
    fit = sum(_f(v) for k, v in st.items() if k.startswith("phong."))
    if "flakes" not in st or not fit > 0:
        return "–"
    share = f"{_f(st['flakes']) / fit:.1%}"
    return share if not row.get("flake_model") else f"{share} (stage ran)"


def verdict(r: dict) -> bool | None:
    """default coat PSNR ≥ paper coat PSNR − :data:`VERDICT_DB`; None without both numbers."""
    d, p = _f(r.get("default", {}).get("psnr_coat")), _f(r.get("paper", {}).get("psnr_coat"))
    if math.isnan(d) or math.isnan(p):
        return None
    return d >= p - VERDICT_DB


def zoo_markdown(names: list[str], results: list[dict], sizes: dict[str, str]) -> str:
    """One row per scene (a failed scene: its reason), then the verdict count."""
    head = ["scene", "size × shots", "default dB", "paper dB", "oracle dB", "default s / α err", "paper s / α err",
            "flake model (default)", "default stage times s", "flake stage / fit", "time default / paper s",
            f"default ≥ paper − {VERDICT_DB} dB"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    ok = total = 0
    for name, r in zip(names, results):
        msg = r.get("not_available") or r.get("error")
        if msg:
            kind = "not available" if "not_available" in r else "error"
            lines.append("| " + " | ".join([name, sizes.get(name, ""), f"{kind}: {msg}"] + [""] * (len(head) - 3)) + " |")
            continue
        d, p = r.get("default", {}), r.get("paper", {})
        v = verdict(r)
        if v is not None:
            total += 1
            ok += bool(v)
        cells = [name, sizes.get(name, ""), _coat_cell(d), _coat_cell(p), _oracle_cell(r), _err_cell(d),
                 _err_cell(p), _flake_cell(d, r.get("truth", {})), _stages_cell(d), _skip_share_cell(d),
                 f"{_f(d.get('time')):.2f} / {_f(p.get('time')):.2f}", "–" if v is None else ("yes" if v else "no")]
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    lines.append(f"default ≥ paper − {VERDICT_DB} dB on {ok} of {total} scenes. *dB*: held-out shots rendered from the "
                 "fitted material against their noise-free renders (torchmetal.metrics.psnr: linear, clipped to "
                 "[0, 1], peak 1), coating only (no sparkle; on flake scenes away from the true flakes); "
                 "*as rendered*: sparkles included. *oracle*: the true specular and flakes with the texture solved "
                 "from the same shots; *flakes redrawn*: the truth with its flakes drawn again from its own statistics "
                 "(what sparkles at random places reach: the yardstick of *as rendered*, bench.zoo.SPARKLE_DRAWS draws); "
                 "*colour ×*: the flakes' mean colour over the drawn flakes'; *sparkles ×*: the left-out sparkle count over the truth's. s / α err: relative error of the mean s and the geometric-mean α "
                 "(– where the truth is not one global Phong lobe). *flake stage / fit*: wall seconds of the flake "
                 "stage over the Phong fit's stages, in the child process (a loaded machine makes it noisy).")
    return "\n".join(lines)


def scene_sizes(ci: bool, names: list[str]) -> dict[str, str]:
    # on use: loads torch (this module imports numpy only)
    from torchmetal.synth.zoo import SCENES, ci_scenes

    scenes = {s.name: s for s in (ci_scenes() if ci else SCENES.values())}
    return {n: f"{scenes[n].size}² × {scenes[n].shots}" for n in names if n in scenes}
