"""ChArUco fiducials: shown on the screen, printed on scale boards and mirror frames, found in images.

A :class:`CharucoLayout` describes a board (squares, square and marker size in its own units, OpenCV's
marker dictionary and the first marker id, so two boards of one dictionary can share an image). Its inner
corners lie at ``((i + 1) s, (j + 1) s)`` in the board frame (OpenCV's: origin at the top-left of the
pattern, x along its columns, y down its rows), numbered row by row as OpenCV numbers ChArUco corners.

On the screen the board is drawn in display pixels (:func:`screen_fiducials`): a square is a whole
number of pixels and its corners lie on pixel boundaries, so a corner's display position is exact:
boundary k of the columns is ``u_x = k p_x`` from the left edge, boundary k of the rows ``u_y = H - k p_y``
from the bottom (docs/conventions.md#screen-positions).

Pure functions of arrays (OpenCV's ``aruco`` module); no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class CharucoLayout:
    """A ChArUco board.

    Attributes
    ----------
    squares_x, squares_y : int
        Squares across and down.
    square : float
        Side of a square (metres for a printed board, display pixels on the screen).
    marker : float
        Side of a marker, same unit.
    dictionary : str
        OpenCV dictionary name, e.g. ``"DICT_4X4_100"``.
    first_id : int
        Id of the board's first marker (its markers are ``first_id, first_id + 1, ...``).
    """

    squares_x: int
    squares_y: int
    square: float
    marker: float
    dictionary: str = "DICT_4X4_100"
    first_id: int = 0

    def __post_init__(self):
        if int(self.squares_x) < 3 or int(self.squares_y) < 3:
            raise ValueError(f"a ChArUco board needs at least 3 x 3 squares, got {self.squares_x} x {self.squares_y}")
        if not (self.square > 0 and 0 < self.marker < self.square):
            raise ValueError(f"a ChArUco marker ({self.marker}) must be smaller than its square ({self.square})")
        if not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}; use an OpenCV name such as DICT_4X4_100")
        size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList.shape[0]
        if self.first_id < 0 or self.first_id + self.n_markers > size:
            raise ValueError(f"the board's {self.n_markers} markers from id {self.first_id} do not fit in "
                             f"{self.dictionary} ({size} markers)")

    @property
    def n_markers(self) -> int:
        return (int(self.squares_x) * int(self.squares_y)) // 2

    @property
    def n_corners(self) -> int:
        return (int(self.squares_x) - 1) * (int(self.squares_y) - 1)

    def board(self):
        """The OpenCV CharucoBoard."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        ids = np.arange(self.first_id, self.first_id + self.n_markers, dtype=np.int32)
        return cv2.aruco.CharucoBoard((int(self.squares_x), int(self.squares_y)), float(self.square),
                                      float(self.marker), dictionary, ids)

    def corners(self) -> np.ndarray:
        """Board-frame positions (n_corners, 2) of the inner corners, in the board's unit, by corner id."""
        j, i = np.mgrid[1:int(self.squares_y), 1:int(self.squares_x)]
        return np.column_stack([i.ravel(), j.ravel()]).astype(np.float64) * float(self.square)

    def image(self, texels_per_square: int) -> np.ndarray:
        """The board drawn as an image (uint8, 0 black, 255 white), *texels_per_square* per square side, so
        every square edge falls on a texel boundary."""
        n = int(texels_per_square)
        return self.board().generateImage((int(self.squares_x) * n, int(self.squares_y) * n), marginSize=0)

    def to_dict(self) -> dict:
        return {"squares_x": int(self.squares_x), "squares_y": int(self.squares_y), "square": float(self.square),
                "marker": float(self.marker), "dictionary": self.dictionary, "first_id": int(self.first_id)}


def detect_charuco(image: np.ndarray, layout: CharucoLayout) -> tuple[np.ndarray, np.ndarray, int]:
    """The board's inner corners found in *image*.

    Returns
    -------
    ids : (N,) int array
        Corner ids (indices into :meth:`CharucoLayout.corners`).
    image_points : (N, 2) array
        Their image positions, pixels (pixel centres at integers, as OpenCV).
    markers : int
        How many of the board's markers were seen (to tell "no board" from "too little of it").
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        raise ValueError(f"fiducial images must be 8-bit, got {img.dtype}")
    corners, ids, _, marker_ids = cv2.aruco.CharucoDetector(layout.board()).detectBoard(img)
    markers = 0
    if marker_ids is not None:
        seen = np.asarray(marker_ids).ravel()
        markers = int(np.count_nonzero((seen >= layout.first_id) & (seen < layout.first_id + layout.n_markers)))
    if ids is None or len(ids) == 0:
        return np.zeros(0, dtype=int), np.zeros((0, 2)), markers
    return np.asarray(ids, dtype=int).ravel(), np.asarray(corners, dtype=np.float64).reshape(-1, 2), markers


@dataclass(frozen=True)
class ScreenFiducials:
    """A ChArUco board drawn on the screen: its layout (in display pixels) and where it starts.

    Attributes
    ----------
    layout : CharucoLayout
        Squares and markers in display pixels.
    offset_px : (int, int)
        Display column and row of the board's top-left corner.
    width_px, height_px : int
        The display's size.
    """

    layout: CharucoLayout
    offset_px: tuple[int, int]
    width_px: int
    height_px: int

    def image(self) -> np.ndarray:
        """The display image (uint8, rows x columns): the board on black."""
        out = np.zeros((self.height_px, self.width_px), dtype=np.uint8)
        board = self.layout.image(int(self.layout.square))
        c0, r0 = self.offset_px
        out[r0:r0 + board.shape[0], c0:c0 + board.shape[1]] = board
        return out

    def positions_m(self, ids: np.ndarray, pitch_x_m: float, pitch_y_m: float) -> np.ndarray:
        """Display positions (N, 2) = (u_x, u_y), metres in the given pitch from the active area's left and
        bottom edges, of the corners *ids*."""
        xy = self.layout.corners()[np.asarray(ids, dtype=int)]
        col = self.offset_px[0] + xy[:, 0]
        row = self.offset_px[1] + xy[:, 1]
        return np.column_stack([col * pitch_x_m, (self.height_px - row) * pitch_y_m])


def screen_fiducials(width_px: int, height_px: int, squares: tuple[int, int] = (12, 7), marker_fraction: float = 0.7,
                     dictionary: str = "DICT_4X4_100", first_id: int = 0) -> ScreenFiducials:
    """The largest board of *squares* that fits the display, centred, squares a whole number of pixels."""
    nx, ny = (int(v) for v in squares)
    square = min(int(width_px) // nx, int(height_px) // ny)
    if square < 12:
        raise ValueError(f"a {nx} x {ny} board does not fit a {width_px} x {height_px} display with squares of at "
                         "least 12 pixels; use fewer squares")
    marker = float(int(round(marker_fraction * square)))
    layout = CharucoLayout(nx, ny, float(square), marker, dictionary, first_id)
    offset = ((int(width_px) - nx * square) // 2, (int(height_px) - ny * square) // 2)
    return ScreenFiducials(layout, offset, int(width_px), int(height_px))
