"""Formatting of bench results: numbers, markdown tables, failed results, speed ratios at equal error."""

from __future__ import annotations

import math

EQUAL_DB = 0.1  # "equal error": held-out PSNR within this many dB
MiB = 2**20


def fmt(x, spec: str = ".3g", none: str = "–") -> str:
    if x is None:
        return none
    if isinstance(x, str):
        try:
            x = float(x)
        except ValueError:
            return x
    if isinstance(x, float) and math.isnan(x):
        return none
    if isinstance(x, float) and math.isinf(x):
        return "∞"
    return format(x, spec)


def md_table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def problem(r: dict) -> str | None:
    """'not available: …' / 'error: …' for a failed result, else None."""
    if "not_available" in r:
        return f"not available: {r['not_available']}"
    if "error" in r:
        return f"error: {r['error']}"
    return None


def _num(x) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return float("nan")
    return v


ERR = "psnr_truth"  # the sweep's primary error: held-out PSNR against the noise-free render of the truth


def primary(r: dict):
    """A result's held-out PSNR against the clean truth, else (old results) against the photos."""
    return r.get(ERR, r.get("psnr_holdout"))


def speed_ratio(tm: dict, base: dict) -> tuple[float | None, str]:
    """Baseline time / torchmetal time when torchmetal's held-out PSNR (against the clean truth,
    :data:`ERR`; the noisy photos where a result lacks it) is equal or better."""
    if problem(tm) or problem(base):
        return None, "n/a"
    p_tm, p_b = _num(primary(tm)), _num(primary(base))
    if math.isnan(p_tm) or math.isnan(p_b):
        return None, "n/a (no PSNR)"
    if p_tm + EQUAL_DB < p_b:
        return None, f"worse error ({p_tm - p_b:+.2f} dB)"
    ratio = _num(base.get("wall_s")) / max(_num(tm.get("wall_s")), 1e-9)
    return ratio, f"{ratio:.1f}×"
