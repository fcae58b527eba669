"""The printable marker frame (docs/design.md §2.6): a ChArUco board with a window where the sample goes.

Geometry lives in :class:`Board` (what ``board.json`` stores, in millimetres on the sheet: origin
top-left, x right, y down). The sheet itself is rasterised exactly: every shape on it (squares,
marker cells, the window outline) is an axis-aligned rectangle on one rectilinear grid, so each
pixel's value is the area-weighted mean reflectance of the cells it covers — one matrix product
``A_y · V · A_xᵀ``, anti-aliased and true to the millimetre at any dpi.

Squares that the window (grown by :data:`BLANK_MARGIN_MM`) touches are left blank, so a band of
plain paper surrounds the window: the white reference the capture balances colours on.
Capture frame (docs/design.md §2.1/2.6): origin at the window centre, x to the sheet's right, y to the
sheet's top, z out of the printed side, metres. The board frame (OpenCV's): origin at the board's
outer top-left corner, x right, y down, z into the sheet, millimetres.
"""

from __future__ import annotations

import functools
import io
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchmetal.errors import CaptureError, InputError

__all__ = ["Board", "BoardError", "make_board", "render_sheet", "sheet_image", "sheet_texture", "write_board", "load_board", "PAPERS"]

FORMAT = "torchmetal-board"
VERSION = 1
PAPERS = {"a4": (210.0, 297.0), "letter": (215.9, 279.4)}
DICTIONARY = "DICT_5X5_250"
SQUARE_MM = 20.0
MARKER_MM = 15.0
EDGE_MM = 12.0  # unprinted sheet margin (printers cannot print to the edge)
BLANK_MARGIN_MM = 4.0  # squares within this of the window are blank: a paper band around it
OUTLINE_MM = 0.3  # the cut line drawn just outside the window
INK = 0.0  # reflectance of printed black, relative to the paper (the sheet stores 0 / 1)


class BoardError(CaptureError):
    """A board description (board.json) or board option is malformed."""


@dataclass(frozen=True)
class Board:
    """The exact geometry of a printed board (the fields of ``board.json``), millimetres.

    Attributes:
        dpi: pixels per inch of board.png (it governs: sheet_mm = pixels × 25.4 / dpi).
        sheet_mm: (width, height) of the sheet.
        window_mm: (x0, y0, x1, y1) of the window, sheet coordinates (origin top-left, y down).
        dictionary: OpenCV ArUco dictionary name; squares: (nx, ny); square_mm, marker_mm: sizes.
        legacy_pattern: OpenCV's CharucoBoard.setLegacyPattern.
        origin_mm: sheet position of the board's outer top-left corner.
    """

    dpi: int
    sheet_mm: tuple[float, float]
    window_mm: tuple[float, float, float, float]
    dictionary: str = DICTIONARY
    squares: tuple[int, int] = (9, 13)
    square_mm: float = SQUARE_MM
    marker_mm: float = MARKER_MM
    legacy_pattern: bool = False
    origin_mm: tuple[float, float] = (15.0, 18.5)
    image: str = "board.png"

    # -- json ---------------------------------------------------------------------------------

    def to_json(self) -> dict:
        return {
            "format": FORMAT, "version": VERSION, "image": self.image, "dpi": self.dpi,
            "sheet_mm": list(self.sheet_mm), "window_mm": list(self.window_mm),
            "charuco": {"dictionary": self.dictionary, "squares": list(self.squares), "square_mm": self.square_mm,
                        "marker_mm": self.marker_mm, "legacy_pattern": self.legacy_pattern,
                        "origin_mm": list(self.origin_mm)},
        }

    @classmethod
    def from_json(cls, meta: object, label: str = "board.json") -> "Board":
        """Parse and check a board.json dictionary; raises :class:`BoardError` (one line)."""
        if not isinstance(meta, dict):
            raise BoardError(f"{label}: expected a JSON object, found {type(meta).__name__}")
        if meta.get("format") != FORMAT:
            raise BoardError(f"{label}: expected format {FORMAT!r}, found {meta.get('format')!r}")
        if meta.get("version") != VERSION:
            raise BoardError(f"{label}: expected version {VERSION}, found {meta.get('version')!r}")
        ch = meta.get("charuco")
        if not isinstance(ch, dict):
            raise BoardError(f"{label}: charuco: expected an object, found {type(ch).__name__}")
        try:
            board = cls(
                dpi=_int(meta.get("dpi"), f"{label}: dpi"), image=str(meta.get("image", "board.png")),
                sheet_mm=tuple(_nums(meta.get("sheet_mm"), 2, f"{label}: sheet_mm")),
                window_mm=tuple(_nums(meta.get("window_mm"), 4, f"{label}: window_mm")),
                dictionary=str(ch.get("dictionary")),
                squares=tuple(_int(v, f"{label}: charuco.squares") for v in _nums(ch.get("squares"), 2, f"{label}: charuco.squares")),
                square_mm=_nums([ch.get("square_mm")], 1, f"{label}: charuco.square_mm")[0],
                marker_mm=_nums([ch.get("marker_mm")], 1, f"{label}: charuco.marker_mm")[0],
                legacy_pattern=bool(ch.get("legacy_pattern", False)),
                origin_mm=tuple(_nums(ch.get("origin_mm"), 2, f"{label}: charuco.origin_mm")),
            )
        except BoardError:
            raise
        return board.check(label)

    def check(self, label: str = "board") -> "Board":
        """Geometric consistency; raises :class:`BoardError`. Returns ``self``."""
        import cv2

        if not hasattr(cv2.aruco, self.dictionary) or not self.dictionary.startswith("DICT_"):
            raise BoardError(f"{label}: charuco.dictionary: expected an OpenCV ArUco dictionary name (e.g. {DICTIONARY}), "
                             f"found {self.dictionary!r}")
        nx, ny = self.squares
        if nx < 3 or ny < 3:
            raise BoardError(f"{label}: charuco.squares: expected at least 3 x 3, found {nx} x {ny}")
        if not 0 < self.marker_mm < self.square_mm:
            raise BoardError(f"{label}: expected 0 < marker_mm < square_mm, found {self.marker_mm:g} and {self.square_mm:g}")
        if self.dpi < 50:
            raise BoardError(f"{label}: dpi: expected at least 50, found {self.dpi}")
        sw, sh = self.sheet_mm
        ox, oy = self.origin_mm
        bw, bh = self.board_mm
        if ox < 0 or oy < 0 or ox + bw > sw + 1e-6 or oy + bh > sh + 1e-6:
            raise BoardError(f"{label}: expected the board ({bw:g} x {bh:g} mm at {ox:g}, {oy:g}) inside the sheet "
                             f"({sw:g} x {sh:g} mm), found it sticking out")
        x0, y0, x1, y1 = self.window_mm
        if not (ox < x0 < x1 < ox + bw and oy < y0 < y1 < oy + bh):
            raise BoardError(f"{label}: window_mm: expected a rectangle inside the board "
                             f"({ox:g}..{ox + bw:g} x {oy:g}..{oy + bh:g} mm), found {list(self.window_mm)}")
        blank = self.blank_squares()
        cols, rows = np.nonzero(blank.T)[0], np.nonzero(blank.T)[1]
        if cols.min() < 1 or rows.min() < 1 or cols.max() > nx - 2 or rows.max() > ny - 2:
            raise BoardError(f"{label}: expected a ring of printed squares around the window, found the window "
                             f"({x1 - x0:g} x {y1 - y0:g} mm) too large for {nx} x {ny} squares of {self.square_mm:g} mm")
        return self

    # -- derived geometry ---------------------------------------------------------------------

    @property
    def board_mm(self) -> tuple[float, float]:
        return self.squares[0] * self.square_mm, self.squares[1] * self.square_mm

    @property
    def window_size_mm(self) -> tuple[float, float]:
        x0, y0, x1, y1 = self.window_mm
        return x1 - x0, y1 - y0

    @property
    def window_centre_board(self) -> tuple[float, float]:
        """The window centre in board coordinates (mm from the board's top-left, y down)."""
        x0, y0, x1, y1 = self.window_mm
        return 0.5 * (x0 + x1) - self.origin_mm[0], 0.5 * (y0 + y1) - self.origin_mm[1]

    def blank_squares(self) -> np.ndarray:
        """(ny, nx) bool: squares left blank (they touch the window grown by BLANK_MARGIN_MM)."""
        nx, ny = self.squares
        s, (ox, oy) = self.square_mm, self.origin_mm
        x0, y0, x1, y1 = self.window_mm
        m = BLANK_MARGIN_MM
        cx = ox + s * np.arange(nx)
        cy = oy + s * np.arange(ny)
        hit_x = (cx < x1 + m) & (cx + s > x0 - m)
        hit_y = (cy < y1 + m) & (cy + s > y0 - m)
        return hit_y[:, None] & hit_x[None, :]

    def corner_ids(self) -> np.ndarray:
        """Ids of the ChArUco corners whose four squares are all printed (the usable ones)."""
        blank = self.blank_squares()
        around = blank[:-1, :-1] | blank[:-1, 1:] | blank[1:, :-1] | blank[1:, 1:]  # (ny-1, nx-1)
        return np.flatnonzero(~around.ravel())

    def corner_points(self) -> np.ndarray:
        """(K, 3) float64 board coordinates (mm, z = 0) of every ChArUco corner, id order."""
        nx, ny = self.squares
        j, i = np.meshgrid(np.arange(1, nx), np.arange(1, ny))
        return np.stack([j.ravel() * self.square_mm, i.ravel() * self.square_mm, np.zeros(j.size)], 1).astype(np.float64)

    def board_to_capture(self, p: np.ndarray) -> np.ndarray:
        """Board points (…, 3) in mm → capture-frame points (…, 3) in metres (a 180° turn about x)."""
        cx, cy = self.window_centre_board
        p = np.asarray(p, dtype=np.float64)
        return np.stack([p[..., 0] - cx, cy - p[..., 1], -p[..., 2]], -1) / 1000.0

    def capture_to_board(self, q: np.ndarray) -> np.ndarray:
        """Capture-frame points (…, 3) in metres → board points (…, 3) in mm."""
        cx, cy = self.window_centre_board
        q = np.asarray(q, dtype=np.float64) * 1000.0
        return np.stack([q[..., 0] + cx, cy - q[..., 1], -q[..., 2]], -1)

    def capture_grid(self, resolution: int) -> tuple[int, int]:
        """(H, W) of the rectified grid: square pixels, the longer window side ``resolution``."""
        w, h = self.window_size_mm
        if w >= h:
            return max(1, round(resolution * h / w)), resolution
        return resolution, max(1, round(resolution * w / h))

    def charuco(self):
        """The matching ``cv2.aruco.CharucoBoard`` (units: mm)."""
        return _charuco(self.dictionary, self.squares, self.square_mm, self.marker_mm, self.legacy_pattern)


@functools.lru_cache(maxsize=8)
def _charuco(dictionary: str, squares: tuple[int, int], square: float, marker: float, legacy: bool):
    import cv2

    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    b = cv2.aruco.CharucoBoard(tuple(int(v) for v in squares), float(square), float(marker), d)
    b.setLegacyPattern(bool(legacy))
    return b


def _nums(v: object, n: int, label: str) -> list[float]:
    ok = isinstance(v, (list, tuple)) and len(v) == n and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
    if not ok:
        raise BoardError(f"{label}: expected {n} finite numbers, found {v!r}"[:200])
    return [float(x) for x in v]  # type: ignore[union-attr]


def _int(v: object, label: str) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v).is_integer() or v <= 0:
        raise BoardError(f"{label}: expected a positive integer, found {v!r}")
    return int(v)


# ---------------------------------------------------------------------------------- making


def make_board(paper: str = "a4", window: tuple[float, float] = (50.0, 50.0), dpi: int = 300) -> Board:
    """A board filling ``paper`` with 20 mm squares, the ``window`` (W, H mm) at its centre.

    Raises:
        BoardError: unknown paper, a window that leaves no ring of markers, dpi < 50.
    """
    if paper not in PAPERS:
        raise BoardError(f"paper: expected one of {list(PAPERS)}, found {paper!r}")
    if not all(isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in window):
        raise BoardError(f"window: expected two positive sizes in mm, found {list(window)}")
    if isinstance(dpi, bool) or not isinstance(dpi, int) or dpi < 50 or dpi > 1200:
        raise BoardError(f"dpi: expected an integer in [50, 1200], found {dpi!r}")
    pw, ph = PAPERS[paper]
    px = (round(pw * dpi / 25.4), round(ph * dpi / 25.4))
    sw, sh = px[0] * 25.4 / dpi, px[1] * 25.4 / dpi  # dpi governs
    nx, ny = int((sw - 2 * EDGE_MM) // SQUARE_MM), int((sh - 2 * EDGE_MM) // SQUARE_MM)
    ox, oy = round(sw - nx * SQUARE_MM) / 2, round(sh - ny * SQUARE_MM) / 2  # whole mm from the edges
    ww, wh = float(window[0]), float(window[1])
    cx, cy = ox + nx * SQUARE_MM / 2, oy + ny * SQUARE_MM / 2
    return Board(dpi=dpi, sheet_mm=(sw, sh), window_mm=(cx - ww / 2, cy - wh / 2, cx + ww / 2, cy + wh / 2),
                 squares=(nx, ny), origin_mm=(ox, oy)).check(f"board ({paper}, window {ww:g} x {wh:g} mm)")


def _grid(board: Board, axis: int) -> np.ndarray:
    """Sorted breakpoints (mm) of every rectangle edge along ``axis`` (0 = x, 1 = y)."""
    import cv2

    n, s, m = board.squares[axis], board.square_mm, board.marker_mm
    o, size = board.origin_mm[axis], board.sheet_mm[axis]
    cells = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary)).markerSize + 2
    k = np.arange(n)[:, None]
    marker = o + k * s + (s - m) / 2 + np.arange(cells + 1)[None, :] * (m / cells)
    w0, w1 = board.window_mm[axis], board.window_mm[axis + 2]
    edges = [0.0, size, *(o + s * np.arange(n + 1)), *marker.ravel(), w0 - OUTLINE_MM, w0, w1, w1 + OUTLINE_MM]
    return np.unique(np.round(np.asarray(edges, dtype=np.float64), 9))


def _cell_values(board: Board, xc: np.ndarray, yc: np.ndarray) -> np.ndarray:
    """Reflectance (ny_cells, nx_cells) in {0, 0.5, 1} at the cell centres (mm, sheet)."""
    import cv2

    b = board.charuco()
    nx, ny = board.squares
    s, m = board.square_mm, board.marker_mm
    ox, oy = board.origin_mm
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    cells = d.markerSize + 2
    # which square holds which marker (OpenCV's order), from the board's own object points
    holder = -np.ones((ny, nx), np.int64)
    for idx, pts in zip(b.getIds().ravel(), b.getObjPoints()):
        tl = np.asarray(pts)[0]
        holder[int(tl[1] // s), int(tl[0] // s)] = int(idx)
    bits = {int(i): cv2.aruco.generateImageMarker(d, int(i), cells) > 127 for i in b.getIds().ravel()}
    blank = board.blank_squares()
    X, Y = np.meshgrid(xc - ox, yc - oy)
    col, row = np.floor(X / s).astype(int), np.floor(Y / s).astype(int)
    inside = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    col_c, row_c = np.clip(col, 0, nx - 1), np.clip(row, 0, ny - 1)
    out = np.ones(X.shape)
    mid = holder[row_c, col_c]
    black_square = inside & (mid < 0) & ~blank[row_c, col_c]
    out[black_square] = INK
    u, v = X - col_c * s - (s - m) / 2, Y - row_c * s - (s - m) / 2
    in_marker = inside & (mid >= 0) & ~blank[row_c, col_c] & (u > 0) & (u < m) & (v > 0) & (v < m)
    cu = np.clip((u / (m / cells)).astype(int), 0, cells - 1)
    cv_ = np.clip((v / (m / cells)).astype(int), 0, cells - 1)
    for i, pattern in bits.items():
        sel = in_marker & (mid == i)
        out[sel] = np.where(pattern[cv_[sel], cu[sel]], 1.0, INK)
    x0, y0, x1, y1 = board.window_mm
    w = OUTLINE_MM
    ring = (X + ox > x0 - w) & (X + ox < x1 + w) & (Y + oy > y0 - w) & (Y + oy < y1 + w)
    ring &= ~((X + ox > x0) & (X + ox < x1) & (Y + oy > y0) & (Y + oy < y1))
    out[ring] = 0.5
    return out


def _overlap(edges: np.ndarray, pixels: int, pitch: float) -> np.ndarray:
    """(pixels, cells) fraction of each pixel [p·pitch, (p+1)·pitch) covered by each cell."""
    p0 = np.arange(pixels)[:, None] * pitch
    lo = np.maximum(p0, edges[None, :-1])
    hi = np.minimum(p0 + pitch, edges[None, 1:])
    return np.clip(hi - lo, 0.0, None) / pitch


def render_sheet(board: Board, dpi: int | None = None) -> np.ndarray:
    """The sheet as (H, W) float64 reflectance in [0, 1] (1 = paper), area-exact at ``dpi``.

    Pixel (i, j) covers the sheet square [j, j+1) × [i, i+1) · 25.4/dpi mm.
    """
    dpi = board.dpi if dpi is None else dpi
    pitch = 25.4 / dpi
    w, h = round(board.sheet_mm[0] / pitch), round(board.sheet_mm[1] / pitch)
    ex, ey = _grid(board, 0), _grid(board, 1)
    values = _cell_values(board, 0.5 * (ex[:-1] + ex[1:]), 0.5 * (ey[:-1] + ey[1:]))
    return _overlap(ey, h, pitch) @ values @ _overlap(ex, w, pitch).T


def _label(board: Board, img: np.ndarray) -> None:
    """Instructions and a 100 mm check bar in the bottom margin (8-bit gray image, in place)."""
    import cv2

    px = board.dpi / 25.4
    ww, wh = board.window_size_mm
    y_bar = board.origin_mm[1] + board.board_mm[1] + 4.0
    x_bar = board.origin_mm[0]
    cv2.rectangle(img, (round(x_bar * px), round(y_bar * px)), (round((x_bar + 100) * px) - 1, round((y_bar + 1) * px) - 1), 0, -1)
    scale = 2.2 * px / 30.0
    text = f"torchmetal board: print at 100 % - the bar is 100 mm - cut out the {ww:g} x {wh:g} mm window"
    cv2.putText(img, text, (round(x_bar * px), round((y_bar + 5.5) * px)), cv2.FONT_HERSHEY_SIMPLEX, scale, 0,
                max(1, round(scale * 2)), cv2.LINE_AA)


def sheet_image(board: Board) -> np.ndarray:
    """board.png's pixels: (H, W) uint8, sRGB-encoded reflectance, labels in the margin."""
    import torch

    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.images import linear_to_srgb

    refl = render_sheet(board)
    img = np.rint(linear_to_srgb(torch.from_numpy(refl)).numpy().clip(0, 1) * 255).astype(np.uint8)
    _label(board, img)
    return img


def write_board(board: Board, out_dir: str | os.PathLike) -> tuple[Path, Path]:
    """Write ``board.png`` (with its dpi) and ``board.json`` into ``out_dir``, atomically each."""
    from PIL import Image

    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.images import atomic_write_bytes

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise BoardError(f"{out}: expected a directory to write the board into, found a file")
    buf = io.BytesIO()
    Image.fromarray(sheet_image(board), mode="L").save(buf, format="PNG", dpi=(board.dpi, board.dpi))
    atomic_write_bytes(out / board.image, buf.getvalue())
    atomic_write_bytes(out / "board.json", (json.dumps(board.to_json(), indent=1) + "\n").encode())
    return out / board.image, out / "board.json"


def load_board(path: str | os.PathLike) -> Board:
    """Read a board.json (or the directory holding one)."""
    p = Path(path)
    if p.is_dir():
        p = p / "board.json"
    if not p.is_file():
        raise BoardError(f"{p}: expected a board.json (from `torchmetal board`), found nothing")
    try:
        meta = json.loads(p.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise BoardError(f"{p}: expected valid JSON, found {type(e).__name__}: {e}"[:200]) from None
    return Board.from_json(meta, str(p))


def sheet_texture(board: Board, board_dir: str | os.PathLike | None = None) -> np.ndarray:
    """The printed sheet as (H, W) float reflectance at board.dpi: board.png decoded when given, else rendered."""
    if board_dir is not None and (Path(board_dir) / board.image).is_file():
        import cv2

        # on use: loads torch (this module imports numpy only)
        from torchmetal.io.images import code_table

        raw = cv2.imdecode(np.fromfile(Path(board_dir) / board.image, np.uint8), cv2.IMREAD_GRAYSCALE)
        if raw is None:
            raise InputError(f"{Path(board_dir) / board.image}: expected a readable PNG, found undecodable data")
        return code_table(8, True)[raw].astype(np.float64)
    # on use: loads torch (this module imports numpy only)
    from torchmetal.io.images import code_table

    return code_table(8, True)[sheet_image(board)].astype(np.float64)
