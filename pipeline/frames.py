"""Frame selection: the sharpest frame of each of N equal sequential bins of a scan.

Sharpness is the variance of the Laplacian of the centre crop (the paper). The authors' code
also subtracted a brightness penalty, |mean V - 105| on 0-255 values, which is an option here.
One pass over the frames keeps only each bin's best image in memory, so a real 36,000-frame
scan fits.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from flowerpose.atomic import write_bytes, write_image
from flowerpose.config import require
from flowerpose.errors import InputError
from flowerpose.jsonio import object_list, read_json, write_json
from flowerpose.log import LOG, Tally
from flowerpose.outputs import OutputFolder, check_output
from flowerpose.scanio import (
    FRAME_PATTERN,
    Intrinsics,
    frame_files,
    iter_frames,
    read_intrinsics,
    read_trajectory,
)
from flowerpose.stopwatch import Stopwatch


@dataclass(frozen=True)
class FrameSelectConfig:
    """How frames are chosen for photogrammetry."""

    count: int = 200
    """Number of bins, one frame chosen from each (the paper: 200 images)."""
    crop_px: int = 400
    """Side of the centre crop the score looks at, pixels (the authors' code: 400 x 400);
    smaller images use their whole shorter side."""
    brightness_penalty: bool = False
    """Subtract |mean V - brightness_target| from the sharpness, as the authors' code did
    (both terms weighted 2.5 there, so equally)."""
    brightness_target: float = 105.0
    """Mean HSV value (0-255) the brightness penalty prefers."""

    def __post_init__(self):
        require(self.count >= 1, "count", f"must be at least 1, got {self.count}")
        require(self.crop_px >= 3, "crop_px", f"must be at least 3 pixels, got {self.crop_px}")


@dataclass(frozen=True)
class ChosenFrame:
    """One frame of frames.json (written by `select_frames`)."""

    index: int
    """The frame's number in the scan."""
    file: str
    """Image path relative to the frames folder."""
    position: np.ndarray | None
    """(3,) recorded camera centre, metres, bed frame; None when frames.json has no pose."""
    rotation: np.ndarray | None
    """(3, 3) camera-to-bed rotation, OpenCV camera axes; None with the position."""

    @property
    def pose(self) -> np.ndarray | None:
        """(4, 4) camera-to-bed matrix, metres, or None."""
        if self.position is None or self.rotation is None:
            return None
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = self.rotation, self.position
        return pose


def is_rotation(matrix: np.ndarray) -> bool:
    """Whether a (3, 3) matrix is a proper rotation (orthonormal to 1e-4, determinant +1)."""
    return bool(np.abs(matrix.T @ matrix - np.eye(3)).max() <= 1e-4
                and np.linalg.det(matrix) > 0)


def read_frames(frames_dir: str | Path, need_poses: bool = True) -> list[ChosenFrame]:
    """frames.json's frames, checked: an integer "index" and a "file" that exists in the
    folder each, and a pose ("position" 3, "rotation" 3 x 3, finite, a proper rotation),
    which may be missing only when `need_poses` is False. Errors name the file and frame."""
    frames_dir = Path(frames_dir)
    path = frames_dir / "frames.json"
    frames = []
    for k, entry in enumerate(object_list(read_json(path), "frames", path, "frame")):
        index, name = entry.get("index"), entry.get("file")
        if isinstance(index, bool) or not isinstance(index, int) or not isinstance(name, str):
            raise InputError(path, f'frame {k} needs an integer "index" and a "file"')
        position = rotation = None
        if "pose" in entry or need_poses:
            try:
                position = np.asarray(entry["pose"]["position"], dtype=np.float64)
                rotation = np.asarray(entry["pose"]["rotation"], dtype=np.float64)
            except (KeyError, TypeError, ValueError):
                raise InputError(path, f'frame {k} needs "file" and "pose" with "position" '
                                 '(3) and "rotation" (3 x 3)') from None
            if position.shape != (3,) or rotation.shape != (3, 3) or not (
                    np.isfinite(position).all() and np.isfinite(rotation).all()):
                raise InputError(path, f"frame {k}: pose needs a finite position (3) and "
                                 "rotation (3 x 3)")
            if not is_rotation(rotation):
                raise InputError(path, f"frame {k}: pose rotation is not a proper rotation")
        if not (frames_dir / name).is_file():
            raise InputError(frames_dir / name, "image listed in frames.json not found")
        frames.append(ChosenFrame(index, name, position, rotation))
    return frames


#: What a frames folder's poses are (frames.json's "poses"): "recorded" by the bot's own
#: scan (exact in the simulator, millimetres off on a real bot), "calibrated" by a
#: photogrammetry run (a COLMAP model), "rough" (a gantry's logged positions and pan/tilt,
#: degrees off), or "none".
POSE_KINDS = ("recorded", "calibrated", "rough", "none")


def pose_kind(frames_dir: str | Path) -> str:
    """frames.json's "poses" (`POSE_KINDS`); "recorded" where it does not say (a scan's)."""
    path = Path(frames_dir) / "frames.json"
    kind = read_json(path).get("poses", "recorded")
    if kind not in POSE_KINDS:
        raise InputError(path, f'"poses" is {kind!r}; one of {", ".join(POSE_KINDS)}')
    return kind


def distinct_views(centres: np.ndarray, axes: np.ndarray, priority: np.ndarray,
                   distance_m: float, angle_deg: float) -> np.ndarray:
    """(N,) bool: the views kept when, of views from within `distance_m` of each other
    looking within `angle_deg` the same way, only the one of highest `priority` counts (a
    greedy pass in priority order: a view is dropped by a kept one only).

    centres: (N, 3) camera centres, metres, bed frame; axes: (N, 3) unit optical axes;
    priority: (N,) higher first, ties to the earlier view.
    """
    centres, axes = np.asarray(centres, np.float64), np.asarray(axes, np.float64)
    near = (np.linalg.norm(centres[:, None] - centres[None], axis=-1) <= distance_m) & (
        axes @ axes.T >= np.cos(np.radians(angle_deg)))
    keep = np.ones(len(centres), bool)
    dropped = np.zeros(len(centres), bool)
    for i in np.argsort(-np.asarray(priority, np.float64), kind="stable"):
        if dropped[i]:
            keep[i] = False
            continue
        dropped |= near[i]
    return keep


def frame_score(rgb: np.ndarray, config: FrameSelectConfig) -> tuple[float, float, float]:
    """(score, Laplacian variance, mean value 0-255) of the centre crop of an RGB image."""
    height, width = rgb.shape[:2]
    side = min(config.crop_px, height, width)
    top, left = (height - side) // 2, (width - side) // 2
    crop = rgb[top:top + side, left:left + side]
    grey = cv2.cvtColor(crop, cv2.COLOR_RGB2GRAY)
    sharpness = float(cv2.Laplacian(grey, cv2.CV_64F).var())
    brightness = float(crop.max(axis=2).mean())
    score = sharpness - abs(brightness - config.brightness_target) \
        if config.brightness_penalty else sharpness
    return score, sharpness, brightness


def _check_size(image: np.ndarray, where: Path | str, intrinsics: Intrinsics) -> None:
    height, width = image.shape[:2]
    if (width, height) != (intrinsics.width, intrinsics.height):
        raise InputError(where, f"is {width}x{height} pixels but the scan's camera.json says "
                         f"{intrinsics.width}x{intrinsics.height}: a scan of two resolutions "
                         "cannot be reconstructed")


#: A JPEG's last two bytes (end of image): a file without them was cut off while written.
JPEG_END = b"\xff\xd9"


def _score_file(path: Path, config: FrameSelectConfig,
                intrinsics: Intrinsics) -> tuple[float, float, float] | None:
    """The frame's score, or None for a damaged file (empty, cut off or undecodable: a
    frame a power cut left half-written), which is left out rather than losing the scan."""
    data = path.read_bytes()
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR) if data else None
    if image is None or (path.suffix.lower() in (".jpg", ".jpeg")
                         and not data.rstrip(b"\x00").endswith(JPEG_END)):
        return None
    _check_size(image, path, intrinsics)
    return frame_score(cv2.cvtColor(image, cv2.COLOR_BGR2RGB), config)


def bin_edges(frame_count: int, bins: int) -> np.ndarray:
    """(bins + 1,) frame-index edges of equal sequential bins."""
    return np.linspace(0, frame_count, bins + 1).round().astype(np.int64)


#: What a frame selection writes in its folder (`outputs.check_output`).
FRAMES_OUTPUTS = ("frames", "camera.json", "frames.json")


def select_frames(scan_dir: Path, out_dir: Path, config: FrameSelectConfig,
                  progress: bool = True, overwrite: bool = False) -> dict:
    """Choose the sharpest frame of each bin; write them to out_dir/frames/ with
    out_dir/frames.json (index, score, pose) and camera.json. Returns frames.json's content.
    out_dir must be new, empty or an earlier frame selection (`outputs`), unless
    `overwrite`; an earlier selection's files are removed first."""
    scan_dir, out_dir = Path(scan_dir), Path(out_dir)
    if not scan_dir.is_dir():
        raise InputError(scan_dir, "scan folder not found")
    scan_at, out_at = scan_dir.resolve(), out_dir.resolve()
    recorded = scan_at / "frames"
    if out_at in (scan_at, recorded) or out_at in scan_at.parents or recorded in out_at.parents:
        raise InputError(out_dir, f"must not be the scan folder {scan_dir}, its frames/, or "
                         "a folder that holds it: choose a folder of its own")
    check_output(out_dir, "frames", overwrite, FRAMES_OUTPUTS)
    trajectory = read_trajectory(scan_dir / "trajectory.csv")
    intrinsics = read_intrinsics(scan_dir / "camera.json")
    total = len(trajectory)
    if total < config.count:
        raise InputError(scan_dir, f"{total} frames recorded, fewer than the {config.count} "
                         "bins asked for")
    row_of = {int(f): k for k, f in enumerate(trajectory.frame)}
    edges = bin_edges(total, config.count)
    bin_of_row = np.searchsorted(edges, np.arange(total), side="right") - 1
    best: dict[int, tuple[float, float, float, int, np.ndarray | None]] = {}
    watch = Stopwatch()
    sources = {int(p.stem.split("_")[-1]): p for p in frame_files(scan_dir)}
    tally = Tally(total if progress else 0, "frames")

    def keep(seen: int, index: int, scored: tuple[float, float, float],
             image: np.ndarray | None) -> None:
        row = row_of[index]
        b = int(bin_of_row[row])
        if b not in best or scored[0] > best[b][0]:
            best[b] = (*scored, row, image)
        tally.advance(1, f"frames: scored {seen}/{total}" if progress and seen % 500 == 0
                      else None)

    with tally:
        if sources:
            # Recorded images: score them on every core (decoding releases the GIL) and copy the
            # winners' files as they are, so no image needs keeping.
            indices = [i for i in sorted(sources) if i in row_of]
            if len(indices) < len(sources):
                LOG.warning(f"note: {scan_dir}: {len(sources) - len(indices)} recorded frames have "
                            "no trajectory.csv row (their poses are unknown) and are left out")
            with ThreadPoolExecutor(os.cpu_count() or 1) as pool:
                scores = pool.map(lambda i: _score_file(sources[i], config, intrinsics), indices)
                damaged = []
                for seen, (index, scored) in enumerate(zip(indices, scores, strict=True), 1):
                    if scored is None:
                        damaged.append(sources[index].name)
                    else:
                        keep(seen, index, scored, None)
            if damaged:
                LOG.warning(f"note: {scan_dir}: {len(damaged)} damaged frames (empty or cut off: "
                            f"{', '.join(damaged[:3])}{', ...' if len(damaged) > 3 else ''}) "
                            "left out")
        else:
            seen = 0
            for index, image in iter_frames(scan_dir):
                if index in row_of:
                    seen += 1
                    _check_size(image, scan_dir / f"video frame {index}", intrinsics)
                    keep(seen, index, frame_score(image, config), image)
    if len(best) < config.count:
        raise InputError(scan_dir, f"frames for only {len(best)} of {config.count} bins: the "
                         "video or frames/ holds fewer frames than trajectory.csv")
    output = OutputFolder(out_dir, "frames", overwrite, FRAMES_OUTPUTS)
    images_dir = out_dir / "frames"
    images_dir.mkdir(parents=True, exist_ok=True)
    output.record(images_dir)
    chosen = []
    for b in range(config.count):
        score, sharpness, brightness, row, image = best[b]
        index = int(trajectory.frame[row])
        name = FRAME_PATTERN.format(index)
        if index in sources:
            write_bytes(images_dir / name, sources[index].read_bytes())  # the recorded bytes
        else:
            write_image(images_dir / name, image, [cv2.IMWRITE_JPEG_QUALITY, 95])
        chosen.append({
            "index": index, "file": f"frames/{name}", "bin": b, "score": round(score, 4),
            "sharpness": round(sharpness, 4), "brightness": round(brightness, 2),
            "t": float(trajectory.t[row]),
            "pose": {"position": trajectory.camera_position[row].tolist(),
                     "rotation": trajectory.camera_rotation[row].tolist()},
            "gantry": trajectory.gantry[row].tolist(), "head": trajectory.head[row].tolist()})
    output.record(write_json(out_dir / "camera.json", intrinsics.to_json()))
    result = {"scan": str(scan_dir), "bins": config.count, "recorded": total,
              "config": {"count": config.count, "crop_px": config.crop_px,
                         "brightness_penalty": config.brightness_penalty,
                         "brightness_target": config.brightness_target},
              "seconds": round(watch.elapsed(), 3), "frames": chosen}
    output.record(write_json(out_dir / "frames.json", result))
    output.finish()
    return result
