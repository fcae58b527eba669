"""``torchmetal board`` and ``torchmetal capture`` (docs/design.md §2.5, 2.6). Only argparse at import."""

from __future__ import annotations

import argparse


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, found {text!r}") from None
    if not v > 0 or v != v or v == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, found {text!r}")
    return v


def _number(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, found {text!r}") from None
    if v != v or abs(v) == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number, found {text!r}")
    return v


def cmd_board(args: argparse.Namespace) -> int:
    # on use: a verb module imports only argparse at the top (CLI start-up)
    from torchmetal.photos.board import make_board, write_board

    board = make_board(args.paper, tuple(args.window), args.dpi)
    png, meta = write_board(board, args.output)
    w, h = board.window_size_mm
    print(f"board: {args.paper} ({board.squares[0]}x{board.squares[1]} squares of {board.square_mm:g} mm), "
          f"window {w:g} x {h:g} mm, {board.dpi} dpi -> {png} + {meta.name} (print at 100 %, no scaling)")
    return 0


def cmd_capture(args: argparse.Namespace) -> int:
    # on use: a verb module imports only argparse at the top (CLI start-up)
    from torchmetal.photos.board import load_board
    from torchmetal.photos.calibrate import Intrinsics
    from torchmetal.photos.capture import capture_from_photos, save_photo_capture

    board = load_board(args.board)
    intr = Intrinsics.load(args.intrinsics) if args.intrinsics else None
    result = capture_from_photos(args.photos, board, flash_offset_mm=args.flash_offset, intrinsics=intr,
                                 resolution=args.resolution, workers=args.workers, progress=not args.quiet)
    plan = None
    if args.plan > 0:  # the next photos to take, on the contact sheet and printed (torchmetal.plan)
        from torchmetal.plan.run import plan_capture

        plan = plan_capture(result.capture, args.plan)
    out = save_photo_capture(result, args.output, plan=plan)
    rep = result.report
    for row in rep["photos"]:
        if not row["used"]:
            print(f"  rejected {row['file']}: {row['reason']}")
    for key, src, what in (("exposure_source", "white_band", "exposure from the white band (no EXIF)"),
                           ("white_balance_source", "set_median", "white balance from the set's median (no usable band)")):
        names = [row["file"] for row in rep["photos"] if row.get(key) == src]
        if names:
            print(f"  {what}: {', '.join(names)}")
    k = result.intrinsics.to_json()
    cap = result.capture
    print(f"capture: {rep['used']} of {len(rep['photos'])} photos, {cap.height}x{cap.width} px over "
          f"{cap.size[0] * 1000:g} x {cap.size[1] * 1000:g} mm, f = {k['fx']:.1f} px ({k['source']}), "
          f"in {rep['seconds']:.1f} s -> {out} (check {out}/contact.png)")
    if plan is not None:
        import numpy as np

        from torchmetal.plan.run import hand_held

        board = result.board
        for k, cam in enumerate(plan.cameras.tolist()):
            b = board.capture_to_board(np.array(cam[:3]))
            print(f"  next photo {k + 1}: phone {hand_held(cam)} (camera at board ({b[0]:.0f}, {b[1]:.0f}, {b[2]:.0f}) mm, "
                  f"aimed at the window's centre)")
    return 0


def register(sub) -> None:
    """Add the ``board`` and ``capture`` verbs to the ``torchmetal`` sub-parsers."""
    b = sub.add_parser("board", help="write a printable ChArUco board with a window for the sample",
                       description="Writes DIR/board.png (print at 100 %%) and DIR/board.json (its exact geometry).")
    b.add_argument("-o", "--output", required=True, help="directory to write board.png and board.json into")
    b.add_argument("--paper", choices=["a4", "letter"], default="a4")
    b.add_argument("--window", nargs=2, type=_positive, default=[50.0, 50.0], metavar=("W", "H"),
                   help="window size in mm (default: %(default)s)")
    b.add_argument("--dpi", type=int, default=300, help="resolution of board.png (default: %(default)s)")
    b.set_defaults(func=cmd_board)

    c = sub.add_parser("capture", help="phone photos of the board → a capture directory (+ report, contact sheet)",
                       description="Detects the board in every photo, calibrates the camera from the set (or reads "
                                   "--intrinsics), finds each pose and the flash, rectifies the window and writes a "
                                   "capture (docs/design.md §2.1) with report.json, intrinsics.json and contact.png.")
    c.add_argument("photos", nargs="+", help="photos (JPEG with EXIF), in shot order")
    c.add_argument("--board", required=True, help="the board.json written by `torchmetal board`")
    c.add_argument("-o", "--output", required=True, help="capture directory to write")
    c.add_argument("--flash-offset", nargs=3, type=_number, default=[0.0, 0.0, 0.0], metavar=("DX", "DY", "DZ"),
                   help="flash position in the camera frame, mm (x right, y down, z forward; default: at the lens)")
    c.add_argument("--intrinsics", help="intrinsics.json of an earlier capture (skip the calibration)")
    c.add_argument("--resolution", type=int, default=512, help="pixels along the window's longer side (default: %(default)s)")
    c.add_argument("--workers", type=int, default=None, help="threads for decoding and detection (default: up to 4)")
    c.add_argument("--plan", type=int, default=2, metavar="K",
                   help="suggest the next K photos (contact sheet and printout; 0: none; default: %(default)s)")
    c.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    c.set_defaults(func=cmd_capture)
