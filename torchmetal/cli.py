"""``torchmetal`` command line: a thin layer over the library (docs/design.md §2.5).

Every verb has ``--help``; bad input exits with status 2 and one line on stderr, never a
traceback. Heavy imports happen inside the verbs so ``--help`` stays instant.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from torchmetal.config import add_fit_arguments, check_tiled, config_from_args
from torchmetal.errors import TorchmetalError
from torchmetal.formats import FORMATS, default_output, export_material

if TYPE_CHECKING:
    from torchmetal.io.capture import Capture
    from torchmetal.pipeline import PipelineResult
    from torchmetal.scale.tiles import TiledCapture

# Verbs that live beside their feature: each module imports only argparse at the top and has
# ``register(sub)`` that adds its sub-parser(s), whose ``func`` does the heavy imports.
EXTRA_VERBS: tuple[str, ...] = ("torchmetal.viewer.cli", "torchmetal.scale.cli", "torchmetal.photos.cli", "torchmetal.plan.cli")


def _vec(n: int):
    def parse(text: str) -> list[float]:
        parts = text.replace(",", " ").split()
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {n} numbers, found {text!r}") from None
        if len(values) != n:
            raise argparse.ArgumentTypeError(f"expected {n} numbers, found {len(values)} in {text!r}")
        return values

    return parse


def cmd_fit(args: argparse.Namespace) -> int:
    # on use: loads torch; parsing and --help load nothing heavy (tests/test_startup.py)
    from torchmetal.material import save_material

    scratch: list = []
    extra: dict[str, Path] = {}
    try:  # scratch tiles and the ONNX file go, on success or failure (run() skips the interpreter's teardown)
        if args.tile is not None:  # tile by tile from memory-mapped files (torchmetal.scale.tiled), scratch beside the output
            result, capture = _fit_tiled(args, scratch)
        else:
            result, capture = _fit_whole(args)
        if args.tile is None:  # the report's registration and disagreement map (a tiled fit holds no whole capture)
            # on use: loads torch; parsing and --help load nothing heavy (tests/test_startup.py)
            from torchmetal.report.fit_maps import DISAGREEMENT_PNG, add_fit_maps

            png = Path(args.output).with_name(Path(args.output).name + ".disagreement.tmp.png")
            extra[DISAGREEMENT_PNG] = add_fit_maps(result, capture, png)
        if args.export:
            # on use: loads torch; parsing and --help load nothing heavy (tests/test_startup.py)
            from torchmetal.onnx_export import export_onnx

            onnx_path = Path(args.output).with_name(Path(args.output).name + ".renderer.onnx.tmp")
            export_onnx(result.material, onnx_path)
            extra["renderer.onnx"] = onnx_path
        save_material(result.material, args.output, extra_files=extra)
    finally:
        for tmp in scratch:
            tmp.cleanup()
        for p in extra.values():
            p.unlink(missing_ok=True)
    rep = result.report
    flakes = result.material.flakes
    print(
        f"fitted {capture.num_shots} shots {capture.height}x{capture.width} in {rep['total_time']:.2f} s: "
        f"rmse {rep['rmse']:.4g}, s {[round(v, 4) for v in result.material.s.tolist()]}, "
        f"alpha {[round(v, 1) for v in result.material.alpha.tolist()]}{_pm_text(rep.get('uncertainty'))}, lobe {result.material.lobe}, "
        f"flakes {'none' if flakes is None else _density_text(flakes)}{_light_text(rep.get('light'))}; "
        f"skipped: {'; '.join(rep['skipped']) or 'nothing'} -> {args.output}"
    )
    return 0


def _pm_text(unc: dict | None) -> str:
    """The fit line's 90 % intervals of a global specular (issue 43): " (α 80 ± 6 / 81 ± 6 / 79 ± 7, s 0.50 ± 0.01 / …)";
    per cluster they are in the report only; a note when no shot saw a highlight."""
    g = (unc or {}).get("globals")
    if not g or len(g["s"]["value"]) != 1:
        return ""
    if g["method"][0][0] == "unseen":
        return " (no highlight seen: s, alpha not measured)"
    pm = lambda k, f: " / ".join(f"{v:{f}} ± {e:{f}}" if e is not None else f"{v:{f}} (bound)"  # noqa: E731
                                 for v, e in zip(g[k]["value"][0], g[k]["pm"][0]))
    return f" (90 %: α {pm('alpha', '.3g')}, s {pm('s', '.3g')})"


def _light_text(light: dict | None) -> str:
    """The fit line's light calibration, where there is one: ", lights moved by (x, y, z) (flash)" and the like."""
    if not light:
        return ""
    parts = []
    if light.get("flash") is not None:
        parts.append(f"lights moved by ({', '.join(f'{v:.3g}' for v in light['flash'])})")
    if light.get("offsets") is not None:
        parts.append(f"{len(light['offsets'])} lights moved to their photos")
    if light.get("falloff"):
        parts.append(f"flash falloff cos^{light['falloff']:.3g}")
    if light.get("gains") is not None:
        parts.append("per-shot gains")
    return f", {', '.join(parts)} (--light {light.get('chosen', light.get('mode'))})" if parts else ""


def _fit_tiled(args: argparse.Namespace, scratch: list) -> tuple[PipelineResult, TiledCapture]:
    """``fit --tile``: the tiled fit (its scratch directory, beside the output, appended to ``scratch``)."""
    import tempfile

    check_tiled(config_from_args(args, progress=False))  # what the tiled fit supports: torchmetal.config
    # on use: loads torch; parsing and --help load nothing heavy (tests/test_startup.py)
    from torchmetal.scale.tiled import fit_tiled_material

    Path(args.output).resolve().parent.mkdir(parents=True, exist_ok=True)
    out_dir = Path(args.output).resolve().parent
    scratch.append(tempfile.TemporaryDirectory(prefix=f".{Path(args.output).name}.tiles.", dir=out_dir))
    result = fit_tiled_material(
        args.capture, tile=args.tile, scheme=args.scheme, specular=args.specular, flakes=args.flakes, tol=args.tol,
        max_iters=args.max_iters, robust=args.robust, seed=args.seed, progress=not args.quiet, scratch=scratch[0].name,
        engine=args.tile_engine if args.tile_workers > 1 or args.tile_engine == "ray" else None,
        workers=args.tile_workers,
    )
    return result, result.capture


def _fit_whole(args: argparse.Namespace) -> tuple[PipelineResult, Capture]:
    """``fit`` without ``--tile``: the capture loaded, fitted in memory."""
    # on use: loads torch; parsing and --help load nothing heavy (tests/test_startup.py)
    from torchmetal.io.capture import load_capture
    from torchmetal.pipeline import fit_material

    capture = load_capture(args.capture)
    result = fit_material(capture, config_from_args(args, progress=not args.quiet))
    return result, capture


def _density_text(flakes) -> str:
    fitted = flakes.extra.get("density_fitted", flakes.density)
    capped = f" (fitted {fitted:.3g}, drawn at the field's capacity)" if fitted > flakes.density else ""
    return f"density {flakes.density:.3g}/px{capped}"


def cmd_render(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    # on use: loads torch; parsing and --help load nothing heavy (tests/test_startup.py)
    from torchmetal.io.images import linear_to_srgb, write_image
    from torchmetal.material import load_material
    from torchmetal.renderer import MaterialRenderer

    material = load_material(args.material)
    renderer = MaterialRenderer(material, flakes=not args.no_flakes)
    light = torch.tensor([args.light], dtype=torch.float32)
    camera = torch.tensor([args.camera], dtype=torch.float32)
    intensity = torch.tensor([args.intensity], dtype=torch.float32)
    # on use: loads torch; parsing and --help load nothing heavy (tests/test_startup.py)
    from torchmetal.io.capture import check_light_camera

    check_light_camera(light, intensity, camera)
    with torch.inference_mode():
        image = renderer(light, intensity, camera)[0] * args.exposure
    out = Path(args.output)
    if out.suffix.lower() == ".npy":
        write_image(out, image.permute(1, 2, 0).numpy())
    else:
        encoded = linear_to_srgb(image.clamp(0, 1)) if not args.linear else image.clamp(0, 1)
        write_image(out, encoded.permute(1, 2, 0).numpy().astype(np.float32), bits=args.bits)
    print(f"rendered {material.height}x{material.width} -> {out}")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    # on use: loads torch; parsing and --help load nothing heavy (tests/test_startup.py)
    from torchmetal.material import load_material

    material = load_material(args.material)
    out = Path(args.output) if args.output else default_output(args.material, args.format)
    options = {"opset": args.opset} if args.format == "onnx" else {}
    if args.format == "web":
        options = {"capture": args.capture, "webgpu": args.webgpu}
    elif args.format in ("gltf", "glb", "mtlx", "usd") and args.capture:
        options = {"capture": args.capture}  # fit the engine lobe over the capture's views
    path = export_material(material, args.format, out, **options)
    size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else path.stat().st_size
    print(f"exported {material.height}x{material.width} material as {args.format} ({size / 2**20:.1f} MiB) -> {path}")
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    # on use: loads torch; parsing and --help load nothing heavy (tests/test_startup.py)
    from torchmetal.synth import synth_capture, write_synth

    flakes = None
    if args.flakes:
        # on use: loads torch; parsing and --help load nothing heavy (tests/test_startup.py)
        from torchmetal.flakes.model import FlakeModel

        flakes = FlakeModel(density=args.flake_density, seed=args.seed)
    result = synth_capture(
        size=args.size, shots=args.shots, seed=args.seed, noise=args.noise, bits=args.bits,
        layout=args.layout, bumpy=args.bumpy, flakes=flakes, spec_clusters=args.spec_clusters,
        texture=args.texture,
    )
    write_synth(result, args.output)
    print(f"wrote synthetic capture ({args.shots} shots, {args.size}x{args.size}) with truth/ -> {args.output}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    # on use: loads torch; parsing and --help load nothing heavy (tests/test_startup.py)
    from torchmetal.demo import run_demo

    run_demo(args.output, size=args.size, quick=args.quick)
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    # on use: loads numpy; parsing and --help load nothing heavy (tests/test_startup.py)
    from torchmetal.bench.__main__ import main as bench_main

    return bench_main(args.rest)


def _bench_argv(argv: list[str]) -> list[str] | None:
    """Arguments after the ``bench`` verb, verbatim (argparse's REMAINDER drops leading options)."""
    return argv[1:] if argv and argv[0] == "bench" else None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="torchmetal", description="Photos of a coated surface → Phong + metallic-flake material → ONNX renderer.")
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    _add_demo(sub)
    _add_fit(sub)
    _add_render(sub)
    _add_export(sub)
    _add_synth(sub)
    for name in EXTRA_VERBS:
        importlib.import_module(name).register(sub)
    _add_bench(sub)
    return p


def _add_demo(sub: argparse._SubParsersAction) -> None:
    """``demo``'s arguments."""
    d = sub.add_parser("demo", help="synthetic capture → fit → render → report (no arguments needed)")
    d.add_argument("-o", "--output", default="torchmetal-demo", help="report folder (default: %(default)s)")
    d.add_argument("--size", type=int, default=256, help="image size of the embedded capture")
    d.add_argument("--quick", action="store_true", help="smaller, faster run")
    d.set_defaults(func=cmd_demo)


def _add_fit(sub: argparse._SubParsersAction) -> None:
    """``fit``'s arguments."""
    f = sub.add_parser("fit", help="fit a material to a capture directory")
    f.add_argument("capture", help="capture directory (docs/design.md §2.1)")
    f.add_argument("-o", "--output", required=True, help="material directory to write")
    add_fit_arguments(f)  # every fit option, from torchmetal.config.FitConfig (the README's table too)
    f.add_argument("--export", action="store_true", help="also write renderer.onnx into the material")
    f.add_argument("--tile", type=int, default=None, metavar="N",
                   help="fit tile by tile (N x N pixels; memory bounded by the tile, not the capture; docs/scale.md)")
    f.add_argument("--tile-workers", type=int, default=1, metavar="W",
                   help="with --tile: tile tasks running at once (1: in this process)")
    f.add_argument("--tile-engine", choices=["local", "ray"], default="local",
                   help="with --tile-workers > 1: a process pool or Ray (results do not depend on it)")
    f.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    f.set_defaults(func=cmd_fit)


def _add_render(sub: argparse._SubParsersAction) -> None:
    """``render``'s arguments."""
    r = sub.add_parser("render", help="render a material for one light and camera")
    r.add_argument("material", help="material directory")
    r.add_argument("--light", type=_vec(4), required=True, help="'x y z w' (w=1 point, w=0 direction)")
    r.add_argument("--camera", type=_vec(4), required=True, help="'x y z w' (w=1 position, w=0 orthographic direction)")
    r.add_argument("--intensity", type=_vec(3), default=[1.0, 1.0, 1.0], help="'r g b' light intensity")
    r.add_argument("-o", "--output", required=True, help=".png (sRGB), .npy (linear float)")
    r.add_argument("--bits", type=int, choices=[8, 16], default=8)
    r.add_argument("--linear", action="store_true", help="write linear values to PNG (no sRGB encoding)")
    r.add_argument("--exposure", type=float, default=1.0, help="scale before encoding")
    r.add_argument("--no-flakes", action="store_true", help="render without sparkles")
    r.set_defaults(func=cmd_render)


def _add_export(sub: argparse._SubParsersAction) -> None:
    """``export``'s arguments."""
    e = sub.add_parser("export", help="export a material: ONNX renderer (default) or an engine format")
    e.add_argument("material", help="material directory")
    e.add_argument("--format", choices=list(FORMATS), default="onnx", help="what to write (default: %(default)s)")
    e.add_argument("-o", "--output", help="output path (default: inside MATERIAL, e.g. MATERIAL/renderer.onnx)")
    e.add_argument("--opset", type=int, default=20, help="ONNX opset (onnx only)")
    e.add_argument("--capture", help="capture directory: web, its photos beside the render; gltf/glb/mtlx/usd, "
                   "the views the specular lobe is fitted over (default 0-60 degrees)")
    e.add_argument("--webgpu", action="store_true", help="also copy onnxruntime-web's WebGPU build (web only)")
    e.set_defaults(func=cmd_export)


def _add_synth(sub: argparse._SubParsersAction) -> None:
    """``synth``'s arguments."""
    s = sub.add_parser("synth", help="write a synthetic capture with ground truth")
    s.add_argument("-o", "--output", required=True, help="capture directory to write")
    s.add_argument("--size", type=int, default=256)
    s.add_argument("--shots", type=int, default=12)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--noise", type=float, default=0.0, help="noise std relative to the image mean")
    s.add_argument("--bits", type=int, choices=[8, 16], default=16)
    s.add_argument("--layout", default="ring", choices=["ring", "hemisphere", "grazing", "near", "far"])
    s.add_argument("--texture", default="auto", choices=["auto", "procedural", "photo"])
    s.add_argument("--bumpy", action="store_true", help="add a bumpy normal map")
    s.add_argument("--flakes", action="store_true", help="add metallic flakes with known statistics")
    s.add_argument("--flake-density", type=float, default=0.003, help="flakes per pixel")
    s.add_argument("--spec-clusters", type=int, default=1, help="regions with their own specular terms")
    s.set_defaults(func=cmd_synth)


def _add_bench(sub: argparse._SubParsersAction) -> None:
    """``bench``: everything after the verb goes to ``torchmetal.bench``."""
    b = sub.add_parser("bench", help="benchmark run time against error (see: torchmetal bench --help)", add_help=False)
    b.add_argument("rest", nargs=argparse.REMAINDER)
    b.set_defaults(func=cmd_bench)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    rest = _bench_argv(argv)
    args = build_parser().parse_args(argv if rest is None else ["bench"])
    if rest is not None:
        args.rest = rest
    try:
        return int(args.func(args) or 0)
    except TorchmetalError as e:
        print(f"torchmetal {args.verb}: error: {e}", file=sys.stderr)
        return 2
    except (OSError, ValueError) as e:
        print(f"torchmetal {args.verb}: error: {type(e).__name__}: {e}".splitlines()[0], file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"torchmetal {args.verb}: interrupted", file=sys.stderr)
        return 130


def run() -> None:
    """The console entry point: :func:`main`, then an exit without the interpreter's teardown.

    With torch loaded, teardown takes ~0.6 s and does nothing a finished command needs
    (``python -c "import torch"``: 1.8 s, 1.2 s with ``os._exit``): the outputs are written and
    closed (atomic renames), temporary files removed, and the streams are flushed here.
    """
    code = main()  # --help and usage errors leave by argparse's SystemExit, before torch is imported
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    run()
