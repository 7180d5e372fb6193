"""The scan folder: what a scan records and every later stage reads (DESIGN.md).

    scan.json         manifest: source, plant position, path parameters, progress
    camera.json       intrinsics: {"model": "PINHOLE", "width", "height", "fx", "fy", "cx",
                      "cy", "fps"}
    trajectory.csv    one row per recorded frame (TRAJECTORY_COLUMNS)
    frames/           frame_000000.jpg, ... (what the camera recorded, in order), and/or
    video.mp4         the same frames as a video

Trajectory units: seconds, metres and radians in the bed frame. The camera pose is
camera-to-bed with OpenCV camera axes (x right, y down, z forward along the optical axis),
as a position and a unit quaternion (w, x, y, z).
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowerpose.errors import InputError
from flowerpose.jsonio import read_json
from flowerpose.log import LOG

TRAJECTORY_COLUMNS = ("frame", "t", "x", "y", "z", "yaw", "pitch",
                      "cam_x", "cam_y", "cam_z", "qw", "qx", "qy", "qz")
"""frame index, time (s), gantry tool-mount position (m), head yaw and pitch (rad),
camera position (m), camera-to-bed rotation quaternion."""
FRAME_PATTERN = "frame_{:06d}.jpg"


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels; the image is width x height."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    fps: float = 30.0
    estimated: bool = False
    """True where nobody calibrated the camera (a default or EXIF focal length, no
    distortion known): the sparse stage then refines the focal length and a distortion."""

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) camera matrix K."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def scaled(self, width: int, height: int) -> Intrinsics:
        """The same camera at another resolution (the field of view kept)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fx * sx, self.fy * sy, self.cx * sx,
                          self.cy * sy, self.fps, self.estimated)

    def to_json(self) -> dict:
        data = {"model": "PINHOLE", "width": self.width, "height": self.height,
                "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy, "fps": self.fps}
        return {**data, "estimated": True} if self.estimated else data


def read_intrinsics(path: Path) -> Intrinsics:
    """camera.json to Intrinsics, checked."""
    data = read_json(path)
    try:
        values = {k: float(data[k]) for k in ("fx", "fy", "cx", "cy")}
        width, height = int(data["width"]), int(data["height"])
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(path, f"camera.json needs width, height, fx, fy, cx, cy ({err})") \
            from None
    if width <= 0 or height <= 0 or values["fx"] <= 0 or values["fy"] <= 0 or not all(
            np.isfinite(list(values.values()))):
        raise InputError(path, "intrinsics must be positive and finite")
    if data.get("model", "PINHOLE") != "PINHOLE":
        raise InputError(path, f"camera.json is a {data['model']} camera: a frames folder's "
                         "camera is a pinhole (flowerpose frames --images undistorts)")
    return Intrinsics(width, height, fps=float(data.get("fps", 30.0)),
                      estimated=data.get("estimated") is True, **values)


@dataclass(frozen=True)
class Trajectory:
    """trajectory.csv as arrays, one row per frame."""

    frame: np.ndarray
    """(F,) int frame indices."""
    t: np.ndarray
    """(F,) seconds since the scan started."""
    gantry: np.ndarray
    """(F, 3) tool-mount position, metres, bed frame."""
    head: np.ndarray
    """(F, 2) yaw, pitch, radians."""
    camera_position: np.ndarray
    """(F, 3) metres, bed frame."""
    camera_rotation: np.ndarray
    """(F, 3, 3) camera-to-bed rotations (columns: camera x, y, z axes in the bed frame)."""

    def __len__(self) -> int:
        return len(self.frame)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (w, x, y, z) to (..., 3, 3) rotation matrices."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, float)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]].reshape(-1, 4)).as_matrix().reshape(
        q.shape[:-1] + (3, 3))


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices to (..., 4) unit quaternions (w, x, y, z), w >= 0."""
    from scipy.spatial.transform import Rotation

    rotation = np.asarray(rotation, float)
    xyzw = Rotation.from_matrix(rotation.reshape(-1, 3, 3)).as_quat()
    wxyz = xyzw[:, [3, 0, 1, 2]] * np.where(xyzw[:, 3:4] < 0, -1.0, 1.0)
    return wxyz.reshape(rotation.shape[:-2] + (4,))


def read_trajectory(path: Path) -> Trajectory:
    """trajectory.csv, checked: the header, numbers, finite values, increasing frames."""
    try:
        with open(path, newline="") as handle:
            text = handle.read()
    except FileNotFoundError:
        raise InputError(path, "file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(path, f"cannot read ({getattr(err, 'strerror', None) or err})") from None
    lines = text.splitlines(keepends=True)
    if len(lines) > 1 and not lines[-1].endswith("\n"):
        # Rows are written whole, newline last: a last line without one was cut off by an
        # interruption and may hold a value cut short. The next recording drops it too.
        LOG.warning(f"note: {path}: the last row, cut off by an interruption, is ignored")
        lines = lines[:-1]
    reader = csv.reader(lines)
    header = next(reader, None)
    rows = [row for row in reader if row]
    if header is None or tuple(h.strip() for h in header) != TRAJECTORY_COLUMNS:
        raise InputError(path, f"expected the header {','.join(TRAJECTORY_COLUMNS)}")
    wrong = next((k for k, row in enumerate(rows) if len(row) != len(TRAJECTORY_COLUMNS)), None)
    if wrong is not None:
        raise InputError(path, f"row {wrong + 1} has {len(rows[wrong])} values, not "
                         f"{len(TRAJECTORY_COLUMNS)}")
    try:
        table = np.array(rows, dtype=np.float64).reshape(-1, len(TRAJECTORY_COLUMNS))
    except ValueError:
        raise InputError(path, "every value must be a number") from None
    if not np.isfinite(table).all():
        raise InputError(path, "NaN or infinite values")
    still = np.flatnonzero(np.linalg.norm(table[:, 10:14], axis=1) < 0.5)
    if len(still):
        raise InputError(path, f"row {still[0] + 1} (frame {int(table[still[0], 0])}): the camera "
                         "rotation's quaternion is not a unit quaternion (it is near zero)")
    frame = table[:, 0].astype(np.int64)
    table, frame = _without_repeats(path, table, frame)
    if len(frame) and np.any(np.diff(frame) <= 0):
        raise InputError(path, "frame indices must increase: the table is damaged; record "
                         "the scan again into a new folder")
    return Trajectory(frame, table[:, 1], table[:, 2:5], table[:, 5:7], table[:, 7:10],
                      quaternion_to_matrix(table[:, 10:14]))


def open_rows(path: Path, header: tuple[str, ...]):
    """(file, csv writer) appending to a scan folder's CSV table: a row cut off by an
    interruption is dropped first, so the table stays readable, and a new table gets its
    header. Write a row only after what it describes is on disk, and flush after each."""
    path = Path(path)
    if path.exists():
        text = path.read_bytes()
        if text and not text.endswith(b"\n"):
            with open(path, "r+b") as handle:
                handle.truncate(text.rfind(b"\n") + 1)
    new = not path.exists() or path.stat().st_size == 0  # after the cut: a lost header too
    handle = open(path, "a", newline="")  # noqa: SIM115 - the caller closes it
    writer = csv.writer(handle)
    if new:
        writer.writerow(header)
        handle.flush()
    return handle, writer


def _without_repeats(path: Path, table: np.ndarray,
                     frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The table without rows that repeat an earlier row exactly (a batch written twice by
    an interruption, in scans recorded before that was fixed), with a note on stderr; a
    frame index repeated with other values is a damaged table."""
    _, first, inverse = np.unique(frame, return_index=True, return_inverse=True)
    if len(first) == len(frame):
        return table, frame
    if not np.array_equal(table, table[first[inverse]]):
        raise InputError(path, "a frame index appears twice with different values: the "
                         "table is damaged; record the scan again into a new folder")
    keep = np.zeros(len(frame), bool)
    keep[first] = True
    LOG.warning(f"note: {path}: {len(frame) - len(first)} repeated rows (a batch written "
                "twice by an interruption) ignored")
    return table[keep], frame[keep]


def trajectory_row(frame: int, t: float, gantry: np.ndarray, yaw: float, pitch: float,
                   camera_position: np.ndarray, camera_rotation: np.ndarray) -> list[str]:
    """One trajectory.csv row in fixed-point text."""
    values = [t, *gantry, yaw, pitch, *camera_position, *matrix_to_quaternion(camera_rotation)]
    return [str(int(frame))] + [f"{float(v):.9f}" for v in values]


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file from its header, without decoding its pixels."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            return image.size
    except (UnidentifiedImageError, OSError):
        raise InputError(path, "unreadable image (not a JPEG or PNG, or damaged)") from None


def frame_files(scan_dir: Path) -> list[Path]:
    """The recorded frame images of a scan folder, in order."""
    return sorted((Path(scan_dir) / "frames").glob("frame_*.jpg"))


def iter_frames(scan_dir: Path) -> Iterator[tuple[int, np.ndarray]]:
    """(index, RGB uint8 image) for every recorded frame: frames/ if present, else video.mp4."""
    import cv2

    scan_dir = Path(scan_dir)
    files = frame_files(scan_dir)
    if files:
        for path in files:
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                raise InputError(path, "unreadable image")
            yield int(path.stem.split("_")[-1]), cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        return
    video = scan_dir / "video.mp4"
    if not video.exists():
        raise InputError(scan_dir, "no frames/ and no video.mp4: not a scan folder")
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        raise InputError(video, "cannot open the video")
    index = 0
    try:
        while True:
            ok, image = capture.read()
            if not ok:
                break
            yield index, cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
            index += 1
    finally:
        capture.release()
