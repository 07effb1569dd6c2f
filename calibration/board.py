"""Calibration targets: chessboard and ChArUco specs, printable images, corner detection (OpenCV 5).

A spec string names a board completely:
    chessboard:COLSxROWS:SQUARE                      inner corners, square side in metres
    charuco:SQUARES_XxSQUARES_Y:SQUARE:MARKER:DICT    squares, square and marker sides in metres

Detections are in this project's pixel convention: pixel (0, 0)'s centre is (0.5, 0.5). OpenCV's
detectors use integer centres, so detected corners get +0.5 here and nowhere else.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

INCH_M = 0.0254
# Fewer corners than this cannot constrain a pose plus a homography robustly.
MIN_CORNERS = 6


class BoardSpecError(ValueError):
    """A board spec string that does not describe a board."""


@dataclass(frozen=True)
class BoardSpec:
    """`kind` 'chessboard' (cols x rows inner corners) or 'charuco' (cols x rows squares)."""

    kind: str
    cols: int
    rows: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = ""

    def __str__(self) -> str:
        if self.kind == "chessboard":
            return f"chessboard:{self.cols}x{self.rows}:{self.square_m:g}"
        return f"charuco:{self.cols}x{self.rows}:{self.square_m:g}:{self.marker_m:g}:{self.dictionary}"

    @property
    def corner_grid(self) -> tuple[int, int]:
        """Inner-corner grid (cols, rows): a ChArUco board of N x M squares has (N-1) x (M-1)."""
        return (self.cols, self.rows) if self.kind == "chessboard" else (self.cols - 1, self.rows - 1)

    @property
    def num_corners(self) -> int:
        c, r = self.corner_grid
        return c * r

    @property
    def squares(self) -> tuple[int, int]:
        """Squares printed (cols, rows)."""
        return (self.cols + 1, self.rows + 1) if self.kind == "chessboard" else (self.cols, self.rows)

    @property
    def size_m(self) -> tuple[float, float]:
        sx, sy = self.squares
        return sx * self.square_m, sy * self.square_m

    def object_points(self) -> np.ndarray:
        """Board-frame 3D corners [num_corners, 3] (z = 0), row-major, id = index; the same order OpenCV uses."""
        c, r = self.corner_grid
        ij = np.stack(np.meshgrid(np.arange(c), np.arange(r)), -1).reshape(-1, 2)
        # ChArUco's first inner corner is one square in from the board's outer corner.
        off = 0.0 if self.kind == "chessboard" else 1.0
        return np.concatenate([(ij + off) * self.square_m, np.zeros((len(ij), 1))], 1)


def board_up(board_to_rig: np.ndarray) -> np.ndarray:
    """Up [3] (unit, away from gravity) in the rig frame from the pose [4, 4] of a board lying printed face up on
    the conveyor. The board's z axis (x along its rows, y down its columns, as `object_points`) points into the
    board, so up is its -z."""
    normal = np.asarray(board_to_rig, np.float64)[:3, 2]
    length = float(np.linalg.norm(normal))
    if not (np.isfinite(length) and length > 1e-12):
        raise ValueError(f"a board pose without a finite rotation: {board_to_rig!r}")
    return -normal / length


def parse_board(spec: str) -> BoardSpec:
    """Parse 'chessboard:9x6:0.025' or 'charuco:5x7:0.04:0.02:DICT_6X6_250' into a BoardSpec."""
    parts = spec.strip().split(":")
    kind = parts[0].lower()
    try:
        if kind == "chessboard" and len(parts) == 3:
            cols, rows = (int(v) for v in parts[1].lower().split("x"))
            out = BoardSpec("chessboard", cols, rows, float(parts[2]))
        elif kind == "charuco" and len(parts) == 5:
            cols, rows = (int(v) for v in parts[1].lower().split("x"))
            out = BoardSpec("charuco", cols, rows, float(parts[2]), float(parts[3]), parts[4].upper())
        else:
            raise BoardSpecError
    except (BoardSpecError, ValueError):
        raise BoardSpecError(
            f"board spec '{spec}' is not 'chessboard:COLSxROWS:SQUARE_M' or 'charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT_NAME'"
        ) from None
    if out.cols < 2 or out.rows < 2 or not (out.square_m > 0):
        raise BoardSpecError(f"board spec '{spec}' needs at least 2x2 and a positive square size")
    if kind == "charuco":
        if not 0 < out.marker_m < out.square_m:
            raise BoardSpecError(f"board spec '{spec}': the marker must be smaller than the square")
        if not out.dictionary.startswith("DICT_") or not hasattr(cv2.aruco, out.dictionary):
            raise BoardSpecError(f"board spec '{spec}': '{out.dictionary}' is not an OpenCV ArUco dictionary")
        if (out.cols * out.rows) // 2 > cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, out.dictionary)).bytesList.shape[0]:
            raise BoardSpecError(f"board spec '{spec}': the dictionary has too few markers for this board")
    return out


def charuco_board(spec: BoardSpec) -> cv2.aruco.CharucoBoard:
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    return cv2.aruco.CharucoBoard((spec.cols, spec.rows), spec.square_m, spec.marker_m, dictionary)


def board_image(spec: BoardSpec, px_per_square: int, margin_squares: float = 0.5) -> np.ndarray:
    """Printable board, uint8 gray [H, W], `px_per_square` pixels a square, white quiet zone around it."""
    sx, sy = spec.squares
    margin = int(round(margin_squares * px_per_square))
    w, h = sx * px_per_square, sy * px_per_square
    if spec.kind == "charuco":
        inner = charuco_board(spec).generateImage((w, h), marginSize=0, borderBits=1)
    else:
        ii, jj = np.meshgrid(np.arange(w) // px_per_square, np.arange(h) // px_per_square)
        # The top-left square is black, as in OpenCV's pattern.png.
        inner = np.where((ii + jj) % 2 == 0, 0, 255).astype(np.uint8)
    return cv2.copyMakeBorder(inner, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255)


def board_image_at_dpi(spec: BoardSpec, dpi: float) -> np.ndarray:
    """Board image whose squares print at exactly `spec.square_m` when printed at `dpi`."""
    px = spec.square_m / INCH_M * dpi
    if abs(px - round(px)) > 1e-6 * px:
        # Non-integer squares would print at the wrong size; say which DPI works.
        raise BoardSpecError(
            f"a {spec.square_m * 1000:g} mm square is {px:.3f} px at {dpi:g} DPI; choose a DPI that makes it a whole number of pixels"
        )
    if round(px) < 8:
        raise BoardSpecError(f"{dpi:g} DPI gives {px:.1f} px a square; use at least 8 px a square")
    return board_image(spec, int(round(px)))


@dataclass(frozen=True)
class BoardDetection:
    """Corners found in one image: `ids` [N] (index into spec.object_points()), `uv` [N, 2] (+0.5 convention), `object_points` [N, 3]."""

    ids: np.ndarray
    uv: np.ndarray
    object_points: np.ndarray
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def collinear(self) -> bool:
        """True when all corners lie on one line (no pose and no intrinsics can be solved from them)."""
        p = self.object_points[:, :2] - self.object_points[:, :2].mean(0)
        s = np.linalg.svd(p, compute_uv=False)
        return len(p) < 3 or s[1] <= 1e-9 * max(s[0], 1e-300)

    def coverage(self, cells: int = 8) -> float:
        """Fraction of a cells x cells grid over the image that holds at least one corner."""
        return coverage([self], self.image_size, cells)


def coverage(detections, image_size: tuple[int, int], cells: int = 8) -> float:
    """Fraction of a cells x cells grid over an image of `image_size` (w, h) touched by any detected corner."""
    w, h = image_size
    hit = np.zeros((cells, cells), bool)
    for d in detections:
        ij = np.floor(d.uv / [w, h] * cells).astype(int).clip(0, cells - 1)
        hit[ij[:, 1], ij[:, 0]] = True
    return float(hit.mean())


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Any [H, W] / [H, W, 3|4] image (uint8, uint16 or float in [0, 1], RGB) -> uint8 gray."""
    img = np.asarray(image)
    if img.dtype.kind == "f":
        img = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    elif img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(img)


def detect_board(spec: BoardSpec, image: np.ndarray) -> BoardDetection | None:
    """Corners of `spec` in `image` (any dtype, gray or RGB); None when fewer than MIN_CORNERS are found.

    ChArUco returns every visible corner (occlusion is fine); a chessboard is all-or-nothing.
    """
    gray = to_gray_u8(image)
    h, w = gray.shape
    if spec.kind == "charuco":
        board = charuco_board(spec)
        params = cv2.aruco.DetectorParameters()
        # Contour-refined marker corners seed the ChArUco corner interpolation better than the
        # raw quad corners (benchmarks/results/calibration.md).
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_CONTOUR
        detector = cv2.aruco.CharucoDetector(board, cv2.aruco.CharucoParameters(), params)
        corners, ids, _, _ = detector.detectBoard(gray)
        if ids is None or len(ids) < MIN_CORNERS:
            return None
        ids = ids.reshape(-1).astype(int)
        obj, img = board.matchImagePoints(corners, ids)
        uv = img.reshape(-1, 2).astype(np.float64)
        obj = obj.reshape(-1, 3).astype(np.float64)
    else:
        uv_cv = _find_chessboard(gray, spec.corner_grid)
        if uv_cv is None:
            return None
        ids = np.arange(spec.num_corners)
        uv = uv_cv
        obj = spec.object_points()
    return BoardDetection(ids, uv + 0.5, obj, (w, h))


def _find_chessboard(gray: np.ndarray, grid: tuple[int, int]) -> np.ndarray | None:
    """Chessboard inner corners [N, 2] in OpenCV pixel coordinates, or None."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, grid, flags=flags)
    if not found:
        found, corners = cv2.findChessboardCornersSB(gray, grid, flags=cv2.CALIB_CB_EXHAUSTIVE)
        if not found:
            return None
    corners = corners.reshape(-1, 2).astype(np.float32)
    # OpenCV's samples refine in an 11x11 half-window; small boards need it under half a square.
    spacing = np.linalg.norm(np.diff(corners.reshape(grid[1], grid[0], 2), axis=1), axis=-1).min()
    half = int(np.clip(0.4 * spacing, 2, 11))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    corners = cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2).copy(), (half, half), (-1, -1), criteria)
    return corners.reshape(-1, 2).astype(np.float64)
