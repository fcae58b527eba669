"""``torchmetal plan``'s work: a capture or a material in, DIR/plan.json and DIR/plan.png out.

A capture is fitted first, quickly (downsampled to at most :data:`FIT_SIDE` pixels a side, global Phong
specular: the plan needs the fit's information, not its last digit); a material brings its fit, its noise
model (the report's ``uncertainty.noise``) and, with ``capture=``, the past shots' positions (capture.json
only: no image is read). A material without its capture is planned as if no photo had been taken.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import torch

from torchmetal.errors import InputError
from torchmetal.plan.core import Plan, PlanOptions, Scene, plan_shots

FIT_SIDE = 128


def scene_from_fit(fit, capture, noise: dict | None) -> Scene:
    """A :class:`Scene` from a FitResult and the capture it was fitted to."""
    labels = fit.spec_labels
    s, a = (fit.cluster_s, fit.cluster_alpha) if labels is not None else (fit.s.view(1, 3), fit.alpha.view(1, 3))
    mask = capture.mask.reshape(capture.height, capture.width).bool()
    return Scene(texture=fit.texture.detach().double(), s=s.detach().double(), alpha=a.detach().double(), labels=labels,
                 normals=None if capture.flat else capture.normals.double(), size=capture.size, lobe=fit.lobe,
                 lights=capture.lights.double(), cameras=capture.cameras.double(),
                 intensities=capture.intensities.double(), noise=noise, mask=None if bool(mask.all()) else mask)


def scene_from_capture(path: Path) -> Scene:
    """Fit the capture at ``path`` (downsampled, global specular) and make its :class:`Scene`."""
    from torchmetal.io.capture import load_capture

    return scene_of_capture(load_capture(path))


def scene_of_capture(cap) -> Scene:
    """Fit a loaded :class:`~torchmetal.io.capture.Capture` (downsampled, global specular): its :class:`Scene`."""
    from torchmetal.fit import fit_phong
    from torchmetal.fit.uncertainty import UncertaintyOptions, estimate_uncertainty

    cap = cap.downsampled(max(1, math.ceil(max(cap.height, cap.width) / FIT_SIDE)))
    fit = fit_phong(cap, specular="global", lobe="phong")
    noise = estimate_uncertainty(fit, cap, UncertaintyOptions(jackknife="off")).noise
    return scene_from_fit(fit, cap, noise)


def plan_capture(cap, shots: int = 2) -> Plan:
    """The next ``shots`` positions for a loaded capture (``torchmetal capture``'s contact sheet)."""
    return plan_shots(scene_of_capture(cap), PlanOptions(shots=shots))


def hand_held(camera, light=None) -> str:
    """Where to hold the phone for a planned camera position (capture frame, metres), in words: its height above the
    sample, its offset from the window's centre along the sheet (right/left, towards the top/bottom), its tilt."""
    x, y, z = (float(v) for v in list(camera)[:3])
    tilt = math.degrees(math.atan2(math.hypot(x, y), z))
    parts = [f"{100 * z:.0f} cm up"]
    if abs(x) >= 0.005:
        parts.append(f"{100 * abs(x):.0f} cm {'right' if x > 0 else 'left'}")
    if abs(y) >= 0.005:
        parts.append(f"{100 * abs(y):.0f} cm to the {'top' if y > 0 else 'bottom'}")
    return ", ".join(parts) + f", tilt {tilt:.0f} deg"


def past_shots(capture_dir: Path) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(lights, cameras, intensities) of a capture directory, from its capture.json alone."""
    from torchmetal.io.capture import parse_meta, read_meta

    meta_file = Path(capture_dir) / "capture.json"
    shots = parse_meta(read_meta(meta_file), str(meta_file))[-1]
    f = lambda key: torch.tensor([getattr(s, key) for s in shots], dtype=torch.float64)  # noqa: E731
    return f("light"), f("camera"), f("intensity")


def scene_from_material(path: Path, capture_dir: Path | None) -> Scene:
    """A :class:`Scene` from a material directory (and its capture's positions)."""
    from torchmetal.material import load_material

    m = load_material(path)
    if m.spec_labels is not None and m.cluster_s is not None:
        s, a, labels = m.cluster_s, m.cluster_alpha, m.spec_labels
    else:
        s, a, labels = m.s.view(1, 3), m.alpha.view(1, 3), None
    if capture_dir is not None:
        lights, cams, inten = past_shots(capture_dir)
    else:
        lights, cams, inten = (torch.zeros(0, 4, dtype=torch.float64), torch.zeros(0, 4, dtype=torch.float64),
                               torch.zeros(0, 3, dtype=torch.float64))
    noise = ((m.report or {}).get("uncertainty") or {}).get("noise")
    noise = None if not noise else {k: torch.tensor(v, dtype=torch.float64) for k, v in noise.items()}
    return Scene(texture=m.texture.double(), s=s.double(), alpha=a.double(), labels=labels,
                 normals=None if m.normals is None else m.normals.double(), size=m.size, lobe=m.lobe, lights=lights,
                 cameras=cams, intensities=inten, noise=noise)


def plan_directory(source: str | Path, out_dir: str | Path, *, options: PlanOptions | None = None,
                   capture: str | Path | None = None) -> tuple[Plan, float]:
    """Plan from a capture or material directory; write ``out_dir``/plan.json and plan.png. Returns (plan, the
    seconds the plan itself took: the fit of a capture and the files' reading not included)."""
    src = Path(source)
    if (src / "capture.json").is_file():
        if capture is not None:
            raise InputError(f"plan: --capture is for a material; {src} is a capture already")
        scene = scene_from_capture(src)
    elif (src / "material.json").is_file():
        if capture is not None and not (Path(capture) / "capture.json").is_file():
            raise InputError(f"plan: --capture: expected a capture directory (capture.json), found {capture}")
        scene = scene_from_material(src, None if capture is None else Path(capture))
    else:
        raise InputError(f"plan: expected a capture (capture.json) or a material (material.json) directory, found {src}")
    t0 = time.perf_counter()
    plan = plan_shots(scene, options)
    dt = time.perf_counter() - t0
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "plan.json").write_text(json.dumps(plan.to_json(), indent=1))
    draw_plan(scene, plan, out / "plan.png")
    return plan, dt


def _free_offsets(points, placed: list, size=(16.0, 12.0)) -> list:
    """Label offsets in display points for ``points`` (n, 2) display coordinates: the first of a ring of offsets whose
    label box (``size``) overlaps no box in ``placed`` (display boxes, appended to) — labels of nearby markers
    do not overlap."""
    rings = [(6, 6), (6, -16), (-20, 6), (-20, -16), (6, 22), (-20, 22), (6, -30), (-20, -30), (22, -5), (-36, -5)]
    out = []
    for x, y in points:
        for dx, dy in rings:
            box = (x + dx, y + dy, x + dx + size[0], y + dy + size[1])
            if not any(box[0] < b[2] and b[0] < box[2] and box[1] < b[3] and b[1] < box[3] for b in placed):
                break
        placed.append(box)
        out.append((dx, dy))
    return out


def draw_plan(scene: Scene, plan: Plan, path: Path) -> None:
    """plan.png: the sample with where the highlight has been seen (and where each planned shot puts it), and a top
    view of the past and planned positions in the capture's frame, each planned shot's height, tilt and coverage
    in the legend below it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from torchmetal.plan.core import HOT, HOT_ALPHA

    tex = scene.texture.clamp(0, 1).permute(1, 2, 0).numpy()
    img = np.where(tex <= 0.0031308, 12.92 * tex, 1.055 * np.power(tex, 1 / 2.4) - 0.055)
    w, h = scene.size
    ext = (-w / 2, w / 2, -h / 2, h / 2)
    fig, ax = plt.subplots(1, 2, figsize=(12, 6.2), gridspec_kw={"width_ratios": [1, 1.15]})
    ax[0].imshow(img, extent=ext)
    seen = plan.coverage.numpy().astype(float)
    if plan.inside is not None:  # off the sample: nothing to see, not red
        seen = np.where(plan.inside.numpy(), seen, 1.0)
    ax[0].imshow(np.ma.masked_where(seen > 0, np.ones_like(seen)), extent=ext, cmap="Reds", alpha=0.45, vmin=0, vmax=1.5)
    half = math.degrees(math.acos(HOT ** (1 / HOT_ALPHA)))
    placed: list = []
    for i, m in enumerate(plan.planned_cover.numpy()):
        if m.any():
            yy, xx = np.nonzero(m)
            cx = ext[0] + (xx.mean() + 0.5) / m.shape[1] * w
            cy = ext[3] - (yy.mean() + 0.5) / m.shape[0] * h
            ax[0].contour(np.linspace(ext[0], ext[1], m.shape[1]), np.linspace(ext[3], ext[2], m.shape[0]), m.astype(float),
                          levels=[0.5], colors=[f"C{i % 10}"], linewidths=2)
            (dx, dy), = _free_offsets(ax[0].transData.transform([(cx, cy)]) * 72 / fig.dpi, placed)
            ax[0].annotate(str(i + 1), (cx, cy), textcoords="offset points", xytext=(dx, dy), color="white", fontsize=12,
                           weight="bold", bbox={"boxstyle": "round,pad=0.15", "fc": f"C{i % 10}", "ec": "none"})
    ax[0].set_title(f"red: no photo put the highlight there ({1 - plan.seen():.0%} of the sample)\n"
                    f"highlight: mirror direction within {half:.1f}° (a lobe ≥ α {HOT_ALPHA:g} at half peak)\n"
                    "outlined, numbered: where each planned shot puts it", fontsize=9)
    ax[0].set_xlabel("x")
    ax[0].set_ylabel("y")
    a = ax[1]
    a.add_patch(plt.Rectangle((-w / 2, -h / 2), w, h, fill=False, color="k"))
    xs, ys = [-w / 2, w / 2], [-h / 2, h / 2]
    if scene.cameras.shape[0]:
        pc = scene.cameras[scene.cameras[:, 3] == 1]
        pl = scene.lights[scene.lights[:, 3] == 1]
        a.scatter(pc[:, 0], pc[:, 1], c="0.55", marker="o", s=30, label="past cameras")
        a.scatter(pl[:, 0], pl[:, 1], c="0.3", marker="x", s=30, label="past flashes")
        xs += pc[:, 0].tolist() + pl[:, 0].tolist()
        ys += pc[:, 1].tolist() + pl[:, 1].tolist()
    cams, lts = plan.cameras.tolist(), plan.lights.tolist()
    xs += [c[0] for c in cams] + [lt[0] for lt in lts]
    ys += [c[1] for c in cams] + [lt[1] for lt in lts]
    pad = 0.12 * max(max(xs) - min(xs), max(ys) - min(ys))
    a.set_xlim(min(xs) - pad, max(xs) + pad)
    a.set_ylim(min(ys) - pad, max(ys) + pad)
    a.set_aspect("equal")
    for i, (cam, lt, gain) in enumerate(zip(cams, lts, plan.cover_gain.tolist())):
        tilt = math.degrees(math.atan2(math.hypot(cam[0], cam[1]), cam[2]))
        a.scatter([cam[0]], [cam[1]], c=f"C{i % 10}", marker="o", s=80, zorder=3,
                  label=f"{i + 1}: camera height {cam[2]:.3g}, tilt {tilt:.0f}°, highlight +{gain:.0%}")
        a.scatter([lt[0]], [lt[1]], c=f"C{i % 10}", marker="*", s=60, zorder=3)
    fig.canvas.draw()
    pts = a.transData.transform([(c[0], c[1]) for c in cams]) * 72 / fig.dpi if cams else []
    placed = []
    for i, (dx, dy) in enumerate(_free_offsets(pts, placed)):
        a.annotate(str(i + 1), (cams[i][0], cams[i][1]), textcoords="offset points", xytext=(dx, dy), fontsize=11,
                   weight="bold", color=f"C{i % 10}")
    a.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), fontsize=8, ncol=2, frameon=False)
    a.set_title("top view, capture frame: o camera, * flash (x past)\nplanned shots numbered, best first", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90, bbox_inches="tight")  # the legend below the top view included
    plt.close(fig)


def describe(plan: Plan, seconds: float) -> str:
    """The verb's printout: one line per planned shot (capture frame), best first."""
    lines = [f"planned {len(plan.scores)} shots from {plan.candidates} reachable positions in {seconds:.2f} s "
             f"(highlight seen on {plan.seen():.0%} of the sample so far)"]
    for i, (lt, cm, de, cg) in enumerate(zip(plan.lights.tolist(), plan.cameras.tolist(), plan.error_drop.tolist(),
                                             plan.cover_gain.tolist())):
        lines.append(f"  {i + 1}: camera ({cm[0]:.3f}, {cm[1]:.3f}, {cm[2]:.3f}), flash ({lt[0]:.3f}, {lt[1]:.3f}, {lt[2]:.3f}): "
                     f"expected held-out variance -{de:.0%}, highlight on +{cg:.0%} of the sample")
    lines += [f"  note: {n}" for n in plan.notes]
    return "\n".join(lines)
