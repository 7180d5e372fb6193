"""A printed ChArUco board beside the plant: the scale and the up of a pose-less
reconstruction (`flowerpose marker` prints one; `sfm.py` finds it).

The board lies flat on the table or the soil, face up. Its chessboard corners, identified by
the ArUco markers between them (OpenCV's aruco module), are found in each registered photo,
triangulated with the reconstruction's cameras, and matched to the board's own corner
positions (metres): the similarity between the two makes the model metric, puts z up out of
the board's face and z = 0 on its plane (the table), with the origin at the board's centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from flowerpose.config import require
from flowerpose.errors import InputError
from flowerpose.pipeline.align import Similarity, residuals, umeyama

#: A printable image's resolution, dots per inch.
PRINT_DPI = 300
#: Fewest triangulated corners, and views that see the board, for a scale to be trusted.
MIN_CORNERS, MIN_VIEWS = 6, 3


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: a chessboard with an ArUco marker in each white square."""

    squares_x: int = 7
    """Squares along the board's long side."""
    squares_y: int = 5
    """Squares along its short side (7 x 5 squares of 30 mm fill an A4 page)."""
    square_m: float = 0.03
    """A square's side as printed, metres: measure one and give it here if the printer
    scaled the page."""
    marker_m: float = 0.022
    """An ArUco marker's side, metres (to scale with square_m)."""
    dictionary: str = "DICT_5X5_100"
    """The ArUco dictionary of its markers (cv2.aruco's name)."""

    def __post_init__(self):
        require(self.squares_x >= 3 and self.squares_y >= 3, "squares_x",
                "a board needs at least 3 x 3 squares")
        require(0 < self.marker_m < self.square_m, "marker_m",
                f"must be positive and smaller than square_m ({self.square_m} m)")

    def board(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m,
                                      self.marker_m, dictionary)

    def corners(self) -> np.ndarray:
        """(K, 3) the board's inner corners in its own frame, metres (z = 0 on the board;
        x along the long side, y along the short side as printed, from a corner)."""
        return np.asarray(self.board().getChessboardCorners(), np.float64)


def board_image(spec: BoardSpec, dpi: int = PRINT_DPI, margin_m: float = 0.01) -> np.ndarray:
    """(H, W) uint8 grey image of the board for printing at `dpi` (its squares then
    measure spec.square_m), with a white margin."""
    pixels_per_m = dpi / 0.0254
    square_px = spec.square_m * pixels_per_m
    margin = round(margin_m * pixels_per_m)
    size = (round(spec.squares_x * square_px) + 2 * margin,
            round(spec.squares_y * square_px) + 2 * margin)
    return spec.board().generateImage(size, marginSize=margin)


def find_corners(grey: np.ndarray, spec: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    """(ids (K,), pixels (K, 2)) of the board's corners found in a grey image (none: two
    empty arrays). Pixels with OpenCV's convention: the first pixel's centre at 0."""
    detector = cv2.aruco.CharucoDetector(spec.board())
    corners, ids, _, _ = detector.detectBoard(grey)
    if ids is None or corners is None or len(ids) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2))
    return ids.ravel().astype(np.int64), corners.reshape(-1, 2).astype(np.float64)


def triangulate(rays: list[np.ndarray], cam_from_world: list[np.ndarray]) -> np.ndarray:
    """(3,) the point nearest to all the rays, world frame (linear least squares).

    rays: per view (2,) normalised image coordinates (x / z, y / z in the camera);
    cam_from_world: per view (3, 4) [R | t]."""
    rows = []
    for (x, y), projection in zip(rays, cam_from_world, strict=True):
        rows.append(x * projection[2] - projection[0])
        rows.append(y * projection[2] - projection[1])
    _, _, vt = np.linalg.svd(np.array(rows))
    point = vt[-1]
    return point[:3] / point[3]


def board_similarity(observations: dict[int, list[tuple[np.ndarray, np.ndarray]]],
                     centres: np.ndarray, spec: BoardSpec) -> tuple[Similarity, dict]:
    """The similarity from the model frame to the board frame (metres, z up out of the
    board's face, origin at its centre), from the board's corners seen in the photos.

    observations: per corner id, (normalised image point (2,), cam_from_world (3, 4)) per
    view that saw it; centres: (N, 3) the registered cameras' centres, model frame (they
    tell the board's face, which they look at, from its back). Raises InputError when
    fewer than MIN_CORNERS corners were seen twice."""
    object_points = spec.corners()
    seen = {i: v for i, v in observations.items() if len(v) >= 2 and i < len(object_points)}
    if len(seen) < MIN_CORNERS:
        raise InputError("board", f"{len(seen)} of its corners seen in two photos or more "
                         f"(need {MIN_CORNERS})")
    ids = sorted(seen)
    model = np.array([triangulate([r for r, _ in seen[i]], [p for _, p in seen[i]])
                      for i in ids])
    board = object_points[ids]
    # The board's printed face is toward the cameras: its frame's z is made to point at
    # them (OpenCV's board z points into the face), and the origin moved to its centre.
    centre = object_points.mean(axis=0)
    flip = np.diag([1.0, -1.0, -1.0])
    target = (board - centre) @ flip.T
    similarity = umeyama(model, target)
    if np.mean(similarity.apply(centres)[:, 2]) < 0:
        raise InputError("board", "the cameras are behind the board: it is not the board "
                         "this run looks for, or it lies face down")
    fit = residuals(similarity, model, target, np.ones(len(ids), bool))
    return similarity, {"corners": len(ids), "rms_m": fit["rms_m"],
                        "square_m": spec.square_m}
