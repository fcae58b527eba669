"""The numpy paper scheme as a whole process, the way a user of a plain CPU reference runs it.

``python -m torchmetal.bench.paper_process CAPTURE_DIR OUT.npz`` reads a docs/design.md §2.1 capture
directory with numpy and OpenCV only (no torch: this process pays for no interpreter start-up
that the reference would not have), fits it with :func:`torchmetal.bench.baselines.paper_scheme_numpy`
and writes ``texture`` (3, H, W), ``s`` (3,), ``alpha`` (3,), ``seconds`` and ``iterations`` to
``OUT.npz``. The bench (:mod:`torchmetal.bench.command`) times the whole process beside
``torchmetal fit`` and scores both against the clean truth.

Images: 8- or 16-bit PNG (sRGB decoded by a lookup table of the IEC curve when ``color_space`` is
``"srgb"``, else linear) or float ``.npy``; codes at the maximum are treated as saturated.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from torchmetal.bench.baselines import paper_scheme_numpy


def _srgb_decode(x: np.ndarray) -> np.ndarray:
    """The IEC 61966-2-1 curve, here rather than imported: torchmetal.io.images and torchmetal.synth
    import torch, and this process must not (the tests check it)."""
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def _read(path: Path, srgb: bool) -> tuple[np.ndarray, np.ndarray]:
    """(3, H, W) float32 linear image and (3, H, W) saturated mask."""
    if path.suffix == ".npy":
        a = np.load(path).astype(np.float32)
        return np.moveaxis(a, -1, 0), np.zeros((3,) + a.shape[:2], bool)
    import cv2

    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.ndim != 3 or raw.shape[2] < 3:
        raise SystemExit(f"paper_process: {path}: expected an RGB image, found none")
    raw = raw[..., 2::-1]  # BGR(A) → RGB
    top = float(np.iinfo(raw.dtype).max)
    sat = np.moveaxis(raw == top, -1, 0)
    x = raw.astype(np.float32) / top
    if srgb:  # a 256/65 536-entry table, as any careful CPU reference would decode
        lut = _srgb_decode(np.arange(int(top) + 1, dtype=np.float64) / top).astype(np.float32)
        x = lut[raw]
    return np.moveaxis(x, -1, 0), sat


def read_capture(directory: str | Path) -> SimpleNamespace:
    """A capture-like namespace (images, saturated, normals, lights, intensities, cameras, size)."""
    root = Path(directory)
    meta = json.loads((root / "capture.json").read_text())
    srgb = meta.get("color_space", "srgb") == "srgb"
    imgs, sats = zip(*(_read(root / shot["image"], srgb) for shot in meta["shots"]))
    normals = None
    if meta.get("normals"):
        normals = np.moveaxis(np.load(root / meta["normals"]).astype(np.float32), -1, 0)
    shots = meta["shots"]
    return SimpleNamespace(
        images=np.stack(imgs), saturated=np.stack(sats), normals=normals,
        lights=np.array([s["light"] for s in shots], np.float64),
        intensities=np.array([s.get("light_intensity", [1.0, 1.0, 1.0]) for s in shots], np.float64),
        cameras=np.array([s["camera"] for s in shots], np.float64),
        size=(float(meta["surface"]["width"]), float(meta["surface"]["height"])),
    )


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: python -m torchmetal.bench.paper_process CAPTURE_DIR OUT.npz", file=sys.stderr)
        return 2
    cap = read_capture(args[0])
    r = paper_scheme_numpy(cap)
    out = Path(args[1])
    tmp = out.with_name(out.name + ".tmp.npz")
    np.savez(tmp, texture=r.texture.astype(np.float32), s=r.s, alpha=r.alpha, seconds=r.seconds,
             iterations=r.iterations)
    tmp.replace(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
