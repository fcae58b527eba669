"""Write generated phone photos of a sample lying in a printed board's window (for `torchmetal capture`).

    python scripts/simulate_photos.py BOARD_DIR/board.json -o PHOTOS/ [-n 12] [--flash-offset 12 -4 0]

Uses only the installed torchmetal (torchmetal.photos.simulate: a known smooth texture with a Phong
highlight, hand-held poses, flash beside the lens, EXIF exposure, noise, JPEG), as the photos tests do,
so the plain-pip CI job (scripts/pip_check.sh) can run board → photos → capture end to end.
"""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("board", help="board.json written by `torchmetal board`")
    p.add_argument("-o", "--output", required=True, help="folder to write the JPEG photos into")
    p.add_argument("-n", type=int, default=12, help="number of photos (default: %(default)s)")
    p.add_argument("--flash-offset", nargs=3, type=float, default=[12.0, -4.0, 0.0], metavar=("DX", "DY", "DZ"),
                   help="flash position in the camera frame, mm (default: 12 -4 0)")
    p.add_argument("--size", type=int, default=64, help="texture pixels along each window side (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)

    import torch

    from torchmetal.photos import simulate as S
    from torchmetal.photos.board import load_board

    board = load_board(args.board)
    sample = S.Sample(S.smooth_texture(args.size, args.size, seed=args.seed + 3), torch.tensor([0.45, 0.5, 0.55]),
                      torch.tensor([50.0, 60.0, 70.0]))
    photos = S.phone_photos(args.output, board, sample, n=args.n, seed=args.seed,
                            flash_offset_mm=tuple(args.flash_offset), supersample=1)
    for path in photos.paths:
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
