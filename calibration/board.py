"""The ChArUco calibration board: its geometry, its printable image, and finding it in a picture.

Board frame (OpenCV's): origin at the outer corner of the first square, x along the rows of
squares (image columns of the printed board), y along the columns (image rows, downwards on
the print), z = x × y, into the board. A camera sees the printed face looking along +z.
Chessboard corners lie in z = 0; corner `i` is `board.getChessboardCorners()[i]`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from robonav.pipeline.config import require
from robonav.pipeline.types import FloatArray


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board as printed."""

    squares_x: int = 7
    """Squares along x (columns of the print)."""
    squares_y: int = 5
    """Squares along y (rows of the print)."""
    square_length_m: float = 0.05
    marker_length_m: float = 0.0375
    dictionary: str = "DICT_5X5_100"
    """Name of an OpenCV ArUco dictionary (`cv2.aruco.DICT_...`)."""

    def __post_init__(self) -> None:
        require(self.squares_x >= 3 and self.squares_y >= 3,
                f"board needs at least 3x3 squares, got {self.squares_x}x{self.squares_y}")
        require(0 < self.marker_length_m < self.square_length_m,
                f"board needs 0 < marker_length_m < square_length_m, got {self.marker_length_m}, "
                f"{self.square_length_m}")
        require(hasattr(cv2.aruco, self.dictionary) and self.dictionary.startswith("DICT_"),
                f"board.dictionary must name an OpenCV ArUco dictionary such as DICT_5X5_100, got {self.dictionary!r}")

    @property
    def size_m(self) -> tuple[float, float]:
        """(width along x, height along y) of the squared area [m]."""
        return self.squares_x * self.square_length_m, self.squares_y * self.square_length_m

    @property
    def corner_count(self) -> int:
        return (self.squares_x - 1) * (self.squares_y - 1)


def make_board(spec: BoardSpec) -> cv2.aruco.CharucoBoard:
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, spec.dictionary))
    return cv2.aruco.CharucoBoard((spec.squares_x, spec.squares_y), spec.square_length_m, spec.marker_length_m,
                                  dictionary)


def board_corners_m(spec: BoardSpec) -> FloatArray:
    """(corner_count, 3) chessboard corners in the board frame [m]."""
    return np.asarray(make_board(spec).getChessboardCorners(), dtype=np.float64).reshape(-1, 3)


def board_image(spec: BoardSpec, *, pixels_per_square: int, margin_squares: float = 0.5) -> npt.NDArray[np.uint8]:
    """The printable board, grey levels, with a white margin of `margin_squares` on every side.

    The squared area spans pixels [m, m + squares * pixels_per_square) in both directions,
    with m = round(margin_squares * pixels_per_square).
    """
    margin = int(round(margin_squares * pixels_per_square))
    width = spec.squares_x * pixels_per_square + 2 * margin
    height = spec.squares_y * pixels_per_square + 2 * margin
    return make_board(spec).generateImage((width, height), marginSize=margin, borderBits=1)


@dataclass(frozen=True)
class Detection:
    """Chessboard corners found in one image."""

    ids: npt.NDArray[np.int64]
    """(K,) corner indices into `board_corners_m`."""
    corners_px: FloatArray
    """(K, 2) sub-pixel corner positions, (u, v) with pixel centers at integers."""


def detect_board(spec: BoardSpec, image: npt.NDArray[np.uint8]) -> Detection:
    """ChArUco corners in an 8-bit grey or RGB image; K = 0 when the board is not seen."""
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    detector = cv2.aruco.CharucoDetector(make_board(spec))
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) == 0:
        return Detection(np.empty(0, dtype=np.int64), np.empty((0, 2)))
    return Detection(ids.reshape(-1).astype(np.int64), corners.reshape(-1, 2).astype(np.float64))
