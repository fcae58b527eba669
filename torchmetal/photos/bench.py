"""Time the whole ``capture`` on full-size phone photos (default: 12 photos of 12 MP).

    python -m torchmetal.photos.bench [--dir DIR] [--size 4000 3000] [--shots 12] [--resolution 512] [--cli]

Generates the photos once into DIR (kept for later runs: generation is slow, capture is what is
timed), then runs :func:`~torchmetal.photos.capture.capture_from_photos` and writes the capture
like the CLI does, printing the wall time, the per-photo share and the accuracy against the truth.
With ``--cli`` it times the whole ``torchmetal capture`` command instead, as a fresh process the way
a user runs it (start-up and imports included): wall and CPU seconds (``os.wait4``), the stage times
from its report.json, and the same accuracy.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import time
from pathlib import Path


def generate(out: Path, size: tuple[int, int], shots: int, seed: int = 0):
    import torch

    # on use: loads torch (this module imports nothing heavy)
    from torchmetal.photos import simulate as S
    from torchmetal.photos.board import make_board

    board = make_board("a4", (50.0, 50.0), dpi=300)
    sample = S.Sample(S.smooth_texture(512, 512, seed=3), torch.tensor([0.45, 0.5, 0.55]), torch.tensor([50.0, 60.0, 70.0]))
    t0 = time.perf_counter()
    photos = S.phone_photos(out, board, sample, n=shots, seed=seed, camera=S.phone_camera(size), supersample=1,
                            flash_offset_mm=(12.0, -4.0, 0.0))
    (out / "truth.pkl").write_bytes(pickle.dumps(photos))
    print(f"generated {shots} photos of {size[0]}x{size[1]} in {time.perf_counter() - t0:.1f} s -> {out}")
    return photos


def _rectified_psnr(cap, photos) -> float:
    """The worst shot's PSNR of the rectified image against the direct render, 1 mm inside the window."""
    import numpy as np
    import torch

    # on use: loads torch (this module imports nothing heavy)
    from torchmetal.metrics import psnr
    from torchmetal.photos.simulate import direct_render

    if photos.sample.texture.shape[-2:] != (cap.height, cap.width):
        return float("nan")
    ww, wh = photos.board.window_size_mm
    j, i = np.arange(cap.width), np.arange(cap.height)
    okx = (j * ww / cap.width >= 1) & ((j + 1) * ww / cap.width <= ww - 1)
    oky = (i * wh / cap.height >= 1) & ((i + 1) * wh / cap.height <= wh - 1)
    mask = torch.from_numpy(oky[:, None] & okx[None, :])[None].expand(3, -1, -1)
    return min(psnr(cap.images[k], direct_render(photos, [k])[0], mask=mask) for k in range(cap.num_shots))


def run_cli(out: Path, photos, resolution: int, workers: int | None) -> tuple[dict, object]:
    """Run ``torchmetal capture`` on the photos as a child process; (timings, the capture it wrote)."""
    import subprocess
    import sys

    # on use: loads torch (this module imports nothing heavy)
    from torchmetal.io.capture import load_capture
    from torchmetal.photos.board import write_board

    board_json = write_board(photos.board, out / "board")[1]
    target = out / "cli_capture"
    cmd = [sys.executable, "-m", "torchmetal.cli", "capture", *map(str, photos.paths), "--board", str(board_json),
           "-o", str(target), "--flash-offset", "12", "-4", "0", "--resolution", str(resolution), "-q"]
    if workers:
        cmd += ["--workers", str(workers)]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"torchmetal capture exited with {proc.returncode}")
    rep = json.loads((target / "report.json").read_text())
    timing = {"cli_wall_s": round(wall, 2), "cli_cpu_s": round(usage.ru_utime + usage.ru_stime, 2),
              "cli_max_rss_mb": round(usage.ru_maxrss / 1024), "capture_s": rep["seconds"],
              "stage_s": rep["stage_seconds"]}
    return timing, load_capture(target)


def _in_process(out: Path, photos, resolution: int, workers: int | None) -> tuple[dict, object]:
    """capture_from_photos + save_photo_capture in this process; (timings, the PhotoCapture)."""
    import resource

    # on use: loads numpy (this module imports nothing heavy)
    from torchmetal.photos.capture import capture_from_photos, save_photo_capture

    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    result = capture_from_photos(photos.paths, photos.board, flash_offset_mm=(12.0, -4.0, 0.0),
                                 resolution=resolution, workers=workers)
    t1 = time.perf_counter()
    save_photo_capture(result, out / "capture")
    t2 = time.perf_counter()
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    cpu = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    timing = {"capture_s": round(t1 - t0, 2), "write_s": round(t2 - t1, 2), "total_s": round(t2 - t0, 2),
              "cpu_s": round(cpu, 2), "stage_s": result.report["stage_seconds"]}
    return timing, result


def main(argv: list[str] | None = None) -> int:
    import numpy as np

    p = argparse.ArgumentParser(prog="python -m torchmetal.photos.bench", description=__doc__.splitlines()[0])
    p.add_argument("--dir", default="bench-results/photo-bench", help="where the generated photos live (made if missing)")
    p.add_argument("--size", nargs=2, type=int, default=[4000, 3000], metavar=("W", "H"))
    p.add_argument("--shots", type=int, default=12)
    p.add_argument("--resolution", type=int, default=512)
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--cli", action="store_true", help="time the whole `torchmetal capture` command as a fresh process")
    args = p.parse_args(argv)
    out = Path(args.dir)
    truth = out / "truth.pkl"
    photos = pickle.loads(truth.read_bytes()) if truth.is_file() else generate(out, tuple(args.size), args.shots)
    photos.paths = [out / p.name for p in photos.paths]  # the folder may have moved

    load = [round(v, 2) for v in os.getloadavg()]
    if args.cli:
        # on use: loads numpy (this module imports nothing heavy)
        from torchmetal.photos.calibrate import Intrinsics

        timing, cap = run_cli(out, photos, args.resolution, args.workers)
        k = Intrinsics.load(out / "cli_capture" / "intrinsics.json").matrix
        used = cap.num_shots
    else:
        timing, result = _in_process(out, photos, args.resolution, args.workers)
        cap, k, used = result.capture, result.intrinsics.matrix, result.report["used"]
    kt = photos.intrinsics.matrix
    cams = cap.cameras[:, :3].double().numpy()
    summary = {
        "photos": len(photos.paths), "size": list(photos.intrinsics.image_size), "resolution": args.resolution,
        **timing, "load_avg_1_5_15": load,
        "f_error_pct": round(100 * float(k[0, 0] / kt[0, 0] - 1), 4),
        "principal_point_error_px": [round(float(k[0, 2] - kt[0, 2]), 3), round(float(k[1, 2] - kt[1, 2]), 3)],
        "camera_error_mm_max": round(1000 * float(np.linalg.norm(cams - photos.cameras, axis=1).max()), 3),
        "used": used,
        "rectified_psnr_db_min": round(_rectified_psnr(cap, photos), 2),
    }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
