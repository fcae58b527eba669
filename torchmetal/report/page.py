"""The demo's one-page report (:func:`report_figure`), put together from :mod:`torchmetal.report.panels`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from torchmetal.flakes.model.md import metallic_difference
from torchmetal.io.capture import Capture
from torchmetal.metrics import psnr
from torchmetal.pipeline import PipelineResult, render_shots
from torchmetal.renderer import MaterialRenderer
from torchmetal.report.panels import (
    exposure_for,
    lobe_samples,
    plot_error,
    plot_flakes,
    plot_image,
    plot_lobe,
    plot_shots,
)

if TYPE_CHECKING:
    from matplotlib.figure import Figure


# ---------------------------------------------------------------------------------------------
# the one-page report


def report_figure(
    capture: Capture,
    result: PipelineResult,
    out_png: str | Path | None = None,
    *,
    truth: dict | None = None,
    heldout: Capture | None = None,
    shot: int | None = None,
    flake_shot: int | None = None,
    render_fn: Callable[[Tensor, Tensor, Tensor], Tensor] | None = None,
    heldout_name: str = "held-out shot",
    title: str | None = None,
    dpi: int = 130,
) -> Figure:
    """The demo's one-page figure.

    Args:
        capture: the :class:`~torchmetal.io.capture.Capture` the fit saw.
        result: a :class:`~torchmetal.pipeline.PipelineResult` (``.material``, ``.fit``,
            ``.flakes``).
        out_png: where to save the PNG (None: do not save).
        truth: optional synthetic ground truth (keys ``texture``, ``s``, ``alpha``).
        heldout: optional ``Capture`` of shots left out of the fit; the re-render and error
            panels use its first shot when given (an honest test), else ``capture`` shot ``shot``.
        shot: shot of ``capture`` for the re-render when there is no ``heldout``.
        flake_shot: shot whose flake detections are drawn (default: the one with most detections).
        render_fn: ``render_fn(light, intensity, camera) -> (B,3,H,W)``; default the full material
            renderer (Phong + sparkles).
        heldout_name: how the figure names the held-out shot.
        title: figure title.

    Returns:
        the matplotlib ``Figure`` (closed when saved).
    """
    import matplotlib

    if out_png is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    if render_fn is None:
        render_fn = _material_render_fn(result.material)

    fig = plt.figure(figsize=(13.5, 8.4), dpi=dpi)
    gs = fig.add_gridspec(3, 6, height_ratios=[1, 1.25, 1.25], hspace=0.3, wspace=0.3, top=0.93, bottom=0.03)
    _input_and_fit_rows(fig, gs, capture, result, truth, flake_shot)

    # row 3: re-render beside the photo, error map
    _rerender_row(fig, gs, *_rerender_shot(capture, heldout, shot, heldout_name), result, render_fn)

    if title:
        fig.suptitle(title, fontsize=11, y=0.985)
    if out_png is not None:
        out_png = Path(out_png)
        out_png.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out_png, bbox_inches="tight")
        plt.close(fig)
    return fig


def _rerender_shot(capture: Capture, heldout: Capture | None, shot: int | None,
                   heldout_name: str) -> tuple[Capture, int, str]:
    """The re-render row's capture, shot and name: the held-out shot when there is one, else ``shot`` of
    ``capture`` (default its middle one)."""
    n_shots = capture.images.shape[0]
    if heldout is not None:
        return heldout, 0, heldout_name
    return capture, (n_shots // 2 if shot is None else shot), f"shot {shot if shot is not None else n_shots // 2}"


def _input_and_fit_rows(fig, gs, capture: Capture, result: PipelineResult, truth: dict | None,
                        flake_shot: int | None) -> None:
    """The figure's first two rows: input shots; texture (fit | truth), lobe, flakes."""
    material = result.material
    n_shots = capture.images.shape[0]
    # row 1: input shots
    show = sorted({int(round(i)) for i in np.linspace(0, n_shots - 1, min(6, n_shots))})
    shot_axes = [fig.add_subplot(gs[0, i]) for i in range(6)]
    plot_shots(shot_axes, capture.images, indices=show, labels=[f"input shot {i}" for i in show])

    # row 2: texture (fit | truth), lobe, flakes
    _texture_panel(fig.add_subplot(gs[1, 0:2]), material.texture, truth)
    _lobe_panel(fig.add_subplot(gs[1, 2:4]), capture, material, truth)
    _flakes_panel(fig.add_subplot(gs[1, 4:6]), capture, result, flake_shot)


def _material_render_fn(material):
    """``render_fn(light, intensity, camera)`` of the material's full renderer, without autograd."""
    renderer = MaterialRenderer(material).eval()

    def render_fn(l, e, c):
        with torch.inference_mode():
            return renderer(l, e, c)

    return render_fn


def _texture_panel(ax, tex: Tensor, truth: dict | None) -> None:
    """The fitted texture d(p), beside the true one (and their PSNR) when ``truth`` has it."""
    tex_exp = exposure_for(truth["texture"] if truth is not None and truth.get("texture") is not None else tex, 100.0)
    if truth is not None and truth.get("texture") is not None:
        tt = torch.as_tensor(truth["texture"]).float()
        both = torch.cat([tex.float(), torch.ones(3, tex.shape[1], max(2, tex.shape[2] // 40)), tt], dim=2)
        plot_image(ax, both, f"fitted texture d(p)  |  truth   (PSNR {psnr(tex, tt):.1f} dB)", exposure=tex_exp)
    else:
        plot_image(ax, tex, "fitted texture d(p)", exposure=tex_exp)


def _lobe_panel(ax, capture: Capture, material, truth: dict | None) -> None:
    """The fitted specular lobe per channel, the true one when ``truth`` has global s and α, and the
    photos' specular evidence (:func:`lobe_samples`)."""
    box = ax.get_position()  # leave room for the y label next to the texture panel
    ax.set_position([box.x0 + 0.03, box.y0 + 0.02, box.width - 0.035, box.height - 0.02])
    samples = lobe_samples(capture, material.texture)
    t_sa = None
    if truth is not None and truth.get("s") is not None and truth.get("alpha") is not None:
        t_sa = (torch.as_tensor(truth["s"]), torch.as_tensor(truth["alpha"]))
        if t_sa[0].dim() != 1 or t_sa[1].dim() != 1:
            t_sa = None
    plot_lobe(ax, material.s, material.alpha, truth=t_sa, samples=samples)
    ax.set_title("specular lobe: fit (lines), truth (dashed),\nphoto − fitted diffuse (dots)", fontsize=9)


def _flakes_panel(ax, capture: Capture, result: PipelineResult, flake_shot: int | None) -> None:
    """The flake detections over photo − Phong of ``flake_shot`` (default: the shot with most
    detections), the central quarter of a large image."""
    material = result.material
    n_shots = capture.images.shape[0]
    fl = getattr(result, "flakes", None)
    particles = getattr(fl, "particles", None) if fl is not None else None
    if flake_shot is None:
        flake_shot = _busiest_shot(particles, n_shots)
    phong = render_shots(result.fit, capture.subset([flake_shot]) if hasattr(capture, "subset") else capture)
    if not hasattr(capture, "subset"):
        phong = phong[flake_shot : flake_shot + 1]
    resid = capture.images[flake_shot] - phong[0]
    h, w = resid.shape[-2:]
    zoom = h >= 192 and w >= 192  # small glints: show the central quarter of large images
    window = (h // 4, h // 4 + h // 2, w // 4, w // 4 + w // 2) if zoom else None
    count = plot_flakes(ax, resid, particles, shot=flake_shot, window=window)
    n_all = _num_particles(particles)
    model = getattr(material, "flakes", None)
    ax.set_title(
        f"detected flakes: photo − Phong of shot {flake_shot}" + (", centre" if zoom else "")
        + f"\n{count} detections in this shot, {n_all} in all shots"
        + ("" if model is not None else " (no flake model)"), fontsize=9)


def _rerender_row(fig, gs, src: Capture, k: int, what: str, result: PipelineResult, render_fn) -> None:
    """Row 3: shot ``k`` of ``src``, its re-render under the same light and camera (with the Metallic
    Difference with and without sparkles when the material has flakes) and the error map."""
    material, fit = result.material, result.fit
    photo = src.images[k]
    render = render_fn(src.lights[k : k + 1], src.intensities[k : k + 1], src.cameras[k : k + 1])[0]
    ax_p = fig.add_subplot(gs[2, 0:2])
    ax_r = fig.add_subplot(gs[2, 2:4])
    ax_e = fig.add_subplot(gs[2, 4:6])
    ex = exposure_for(photo)
    plot_image(ax_p, photo, f"photo ({what})", exposure=ex)
    valid = ~src.saturated[k].any(0) if getattr(src, "saturated", None) is not None else None
    if getattr(material, "flakes", None) is not None:
        phong_k = fit.render(src.lights[k : k + 1], src.intensities[k : k + 1], src.cameras[k : k + 1])[0]
        md = metallic_difference(render, photo)
        md0 = metallic_difference(phong_k, photo)
        r_title = f"re-render (Phong + sparkles), same light and camera\nMD {md:.1f} (without sparkles: {md0:.1f}; lower = closer)"
    else:
        r_title = "re-render (Phong), same light and camera"
    plot_image(ax_r, render, r_title, exposure=ex)
    plot_error(ax_e, render, photo, valid=valid, fig=fig)


def _num_particles(particles) -> int:
    return 0 if particles is None else len(particles)


def _busiest_shot(particles, n_shots: int) -> int:
    if particles is None or len(particles) == 0:
        return 0
    return int(torch.bincount(particles.shot.cpu().long(), minlength=n_shots).argmax())
