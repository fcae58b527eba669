"""What ``torchmetal bench`` runs: the :class:`Plan` of sizes, shots and limits (``--full`` and
``--quick``) and the sweep's configurations."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Plan:
    """Sizes and budgets of one benchmark mode."""

    name: str
    base: dict
    resolutions: list[int]
    shot_counts: list[int]
    noises: list[tuple[float, int | None]]
    tols: list[float]
    adam_steps: int
    adam_max_work: int  # Adam runs its full step count only where H·W·N ≤ this
    adam_budget_s: float  # wall-clock cap for Adam elsewhere (None → not run there)
    load_size: int = 1024
    load_shots: int = 16
    fit_size: int = 1024
    fit_shots: int = 16
    skip_size: int = 512
    skip_shots: int = 12
    flake_size: int = 1024
    onnx_size: int = 1024
    real_downsample: int = 1
    real_captures: tuple[str, ...] = ("cards_blue", "yellow_box", "uw_gray_sphere")
    real_max_shots: int | None = None
    real_speculars: tuple[str, ...] = ("global", "clustered", "paper", "paper_model", "light_off", "default")
    realflakes_captures: tuple[str, ...] = ("cards_blue",)
    isolate: bool = True
    timeout_s: float = 1800.0
    holdout: int = 2
    paper_axes: tuple[str, ...] = ("resolution", "tol")  # where torchmetal's own paper scheme also runs
    adam_axes: tuple[str, ...] = ("resolution",)  # where Adam runs (it needs minutes per run at 512²)
    threads: int | None = None  # intra-op threads of every child (None: torch's default)
    zoo_ci: bool = False  # zoo scenes at their ci_scenes() size
    zoo_scenes: tuple[str, ...] | None = None  # None: every scene of the zoo
    full_rows: bool = False  # ``--full`` given: the command section's 2048² rows too
    robust_options: tuple[str, ...] | None = None  # option sets of the robust matrix (None: all)
    robust_scenes: tuple[str, ...] = ("flakes_a", "flakes_b", "flakes_orange", "flakes_half", "sphere_sharp72")
    robust_real: bool = True  # the shared real captures in the matrix and uw_gray_sphere in the share table
    robust_share: bool = True  # the flake-stage share table over every flake-free zoo scene


def full_plan() -> Plan:
    return Plan(
        name="full",
        base=dict(size=512, shots=12, noise=0.01, bits=None, tol=1e-6),
        resolutions=[256, 512, 1024, 2048],
        shot_counts=[4, 8, 12, 16, 32],
        noises=[(0.0, None), (0.01, None), (0.01, 8), (0.03, None)],
        tols=[1e-3, 1e-4, 1e-6, 1e-8],
        adam_steps=2000,
        adam_max_work=512 * 512 * 12,
        adam_budget_s=0.0,
    )


def quick_plan() -> Plan:
    return Plan(
        name="quick",
        base=dict(size=32, shots=6, noise=0.01, bits=None, tol=1e-6),
        resolutions=[32, 48],
        shot_counts=[6],
        noises=[(0.01, None)],
        tols=[1e-6],
        adam_steps=100,
        adam_max_work=48 * 48 * 8,
        adam_axes=("resolution", "shots", "noise"),
        adam_budget_s=0.0,
        load_size=64, load_shots=4, fit_size=48, fit_shots=4, skip_size=32, skip_shots=6,
        flake_size=64, onnx_size=32, real_downsample=8, real_captures=("uw_gray_sphere",), real_max_shots=5,
        real_speculars=("global", "paper", "default"), realflakes_captures=("uw_gray_sphere",), isolate=False,
        timeout_s=120.0, threads=1,
        # three zoo scenes at their ci_scenes() size (a photo texture, two materials, bright flakes): the section's
        # plumbing; the whole CI zoo is fitted once, by tests/bench/test_zoo.py (~3.5 min on 2 cores)
        zoo_ci=True, zoo_scenes=("photo_srgb8", "two_materials", "flakes_bright_hemi"),
        robust_options=("default", "flakes on"), robust_scenes=("sphere_sharp72",), robust_real=False,
        robust_share=False,
    )


def sweep_configs(plan: Plan) -> list[dict]:
    """One-factor-at-a-time sweeps around ``plan.base``; identical configs run once."""
    out: list[dict] = []
    seen: dict[tuple, dict] = {}

    def add(axis: str, **kw) -> None:
        cfg = {**plan.base, **kw}
        key = (cfg["size"], cfg["shots"], cfg["noise"], cfg["bits"], cfg["tol"])
        if key in seen:
            seen[key]["axes"].append(axis)
            return
        cfg["axes"] = [axis]
        seen[key] = cfg
        out.append(cfg)

    for r in plan.resolutions:
        add("resolution", size=r)
    for n in plan.shot_counts:
        add("shots", shots=n)
    for nz, bits in plan.noises:
        add("noise", noise=nz, bits=bits)
    for t in plan.tols:
        add("tol", tol=t)
    return out
