"""Photographs or a video of a plant to a frames folder (`flowerpose frames --images`).

    DIR of JPEG/PNG photos, or a video file
      (+ --colmap MODEL_DIR: a calibrated camera and a pose per photo, COLMAP text or binary)
      (+ --calibration CAMERA.json: the camera, any COLMAP model, distortion included)
      (+ --poses POSES.csv: rough camera positions and pan/tilt, as a gantry logs them)
      -> out_dir/frames/*.jpg   the photos (undistorted to a pinhole where the camera is known)
      -> out_dir/camera.json    pinhole intrinsics; "estimated": true where the camera is
                                not known, which the sparse stage then refines
      -> out_dir/frames.json    one entry per frame, its pose where one was given, and
                                "poses": "calibrated" | "rough" | "none"

Poses are camera-to-world with OpenCV camera axes (x right, y down, z forward), converted to
metres from the unit the user states. A COLMAP model's frame is kept as it is; the rough
poses' frame is the gantry's (z up). Without poses the sparse stage finds them and puts the
cloud upright (`sfm.py`).
"""

from __future__ import annotations

# cv2 before pycolmap (sfm.py says why).
import cv2  # isort: skip

import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

try:
    import pycolmap
except ImportError:  # the [recon] extra is not installed
    pycolmap = None

from flowerpose.atomic import write_bytes, write_image
from flowerpose.config import require
from flowerpose.csvio import read_csv_table
from flowerpose.errors import InputError, missing_extra
from flowerpose.jsonio import read_json, write_json
from flowerpose.log import LOG, Tally
from flowerpose.outputs import check_output, publish, staging_folder
from flowerpose.pipeline.frames import (
    FRAMES_OUTPUTS,
    FrameSelectConfig,
    bin_edges,
    frame_score,
    is_rotation,
)
from flowerpose.processes import reclaim_sigterm
from flowerpose.scanio import Intrinsics, image_size
from flowerpose.stopwatch import Stopwatch

reclaim_sigterm()

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
#: Metres per unit of the poses a user gives.
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}
#: The focal length COLMAP assumes for a camera it knows nothing of, in multiples of the
#: image's longer side (ImageReaderOptions.default_focal_length_factor).
DEFAULT_FOCAL_FACTOR = 1.2
#: The columns of a rough-poses CSV (`read_pose_table`).
POSE_COLUMNS = ("file", "x", "y", "z", "pan", "tilt")


@dataclass(frozen=True)
class PhotoImportConfig:
    """How photographs or a video become a frames folder."""

    count: int = 200
    """A video: the sharpest frame of each of this many equal bins (as for a scan).
    Photographs are all kept: each was taken on purpose."""
    max_size: int | None = None
    """Longest image side written, pixels; larger images are downscaled (the camera with
    them). None keeps the size."""
    units: Literal["m", "cm", "mm"] = "m"
    """The unit of the given poses (a COLMAP model's or the CSV's positions)."""
    jpeg_quality: int = 95
    """JPEG quality of re-encoded images (undistorted or downscaled)."""

    def __post_init__(self):
        require(self.count >= 1, "count", f"must be at least 1, got {self.count}")
        require(self.max_size is None or self.max_size >= 16, "max_size",
                f"must be at least 16 pixels, got {self.max_size}")
        require(self.units in UNITS, "units", f"one of {', '.join(UNITS)}, got {self.units!r}")
        require(1 <= self.jpeg_quality <= 100, "jpeg_quality", "must be 1-100")


@dataclass(frozen=True)
class PosedPhoto:
    """A given pose of one photo: camera-to-world, metres, OpenCV camera axes."""

    position: np.ndarray
    """(3,) camera centre, metres."""
    rotation: np.ndarray
    """(3, 3) camera-to-world rotation (columns: camera x, y, z in the world)."""


def _natural_key(path: Path) -> list:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def list_photos(folder: Path) -> list[Path]:
    """The folder's JPEG and PNG files in natural order (img2 before img10)."""
    photos = sorted((p for p in Path(folder).iterdir()
                     if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES), key=_natural_key)
    if not photos:
        raise InputError(folder, f"no photographs ({', '.join(PHOTO_SUFFIXES)}) in the folder")
    return photos


def _read_rgb(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise InputError(path, "unreadable image (not a JPEG or PNG, or damaged)")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def exif_focal_px(path: Path, width: int, height: int) -> float | None:
    """The focal length in pixels from a photo's EXIF (its 35 mm equivalent, which phones
    write), or None where the EXIF does not say."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            exif = image.getexif().get_ifd(0x8769)  # the Exif sub-IFD
    except OSError:
        return None
    equivalent = exif.get(0xA405)  # FocalLengthIn35mmFilm, mm
    if not equivalent:
        return None
    # The 35 mm equivalent is the focal length a 36 x 24 mm frame would need for the same
    # field of view along the longer side.
    return float(equivalent) / 36.0 * max(width, height)


def video_frames(video: Path, config: FrameSelectConfig) -> list[tuple[int, np.ndarray]]:
    """(frame number, RGB image) of the sharpest frame of each of `config.count` equal bins
    of a video (`frames.frame_score`), in order. Two passes: the first counts the frames
    (a container's own count is often wrong), the second scores them and keeps each bin's
    best image."""
    capture = cv2.VideoCapture(str(video))
    try:
        if not capture.isOpened():
            raise InputError(video, "not a video OpenCV can decode")
        total = 0
        while capture.grab():
            total += 1
    finally:
        capture.release()
    if total == 0:
        raise InputError(video, "no frame decodes: not a video, or damaged")
    if total < config.count:
        raise InputError(video, f"{total} frames, fewer than the {config.count} bins asked for "
                         "(--count)")
    edges = bin_edges(total, config.count)
    best: dict[int, tuple[float, int, np.ndarray]] = {}
    capture = cv2.VideoCapture(str(video))
    size = None
    try:
        with Tally(total, "frames") as tally:
            for index in range(total):
                ok, image = capture.read()
                if not ok:
                    raise InputError(video, f"frame {index} of {total} does not decode")
                if size is None:
                    size = image.shape
                rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
                b = int(np.searchsorted(edges, index, side="right") - 1)
                score = frame_score(rgb, config)[0]
                if b not in best or score > best[b][0]:
                    best[b] = (score, index, rgb)
                tally.advance(1, f"frames: scored {index + 1}/{total}"
                              if (index + 1) % 500 == 0 else None)
    finally:
        capture.release()
    return [(best[b][1], best[b][2]) for b in range(config.count)]


def read_camera_file(path: Path) -> pycolmap.Camera:
    """A calibration file: the project's camera.json (PINHOLE fx, fy, cx, cy), or the same
    with "model" any COLMAP camera model and "params" in COLMAP's order (OPENCV: fx, fy,
    cx, cy, k1, k2, p1, p2)."""
    data = read_json(path)
    model = data.get("model", "PINHOLE")
    try:
        width, height = int(data["width"]), int(data["height"])
        params = data.get("params")
        if params is None:
            if model != "PINHOLE":
                raise KeyError("params")
            params = [data["fx"], data["fy"], data["cx"], data["cy"]]
        camera = pycolmap.Camera.create_from_model_name(1, model, 1.0, width, height)
        camera.params = np.asarray(params, dtype=np.float64)
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(path, f'a calibration needs "width", "height" and "fx", "fy", "cx", '
                         f'"cy" or "model" and "params" ({err})') from None
    if not camera.verify_params() or not np.isfinite(camera.params).all() or width <= 0 \
            or height <= 0 or camera.has_bogus_params(0.01, 100.0, 10.0):
        raise InputError(path, f"{model} with {len(params)} parameters is not a valid camera "
                         "(COLMAP's parameter count and order, positive focal lengths)")
    return camera


def read_colmap_model(model_dir: Path, units: str
                      ) -> tuple[dict[str, pycolmap.Camera], dict[str, PosedPhoto]]:
    """A COLMAP model's camera and pose per image name (the name's last part), poses
    converted to metres from `units`."""
    if not Path(model_dir).is_dir():
        raise InputError(model_dir, "COLMAP model folder not found")
    has_text = (Path(model_dir) / "images.txt").is_file()
    has_binary = (Path(model_dir) / "images.bin").is_file()
    if not (has_text or has_binary):
        raise InputError(model_dir, "not a COLMAP model: no cameras and images (.txt or .bin)")
    try:
        model = pycolmap.Reconstruction(str(model_dir))
    except Exception as err:  # pycolmap raises its own types for a damaged model
        raise InputError(model_dir, f"cannot read the COLMAP model ({err})") from None
    cameras, poses = {}, {}
    for image in model.images.values():
        if not image.has_pose:
            continue
        name = Path(image.name).name
        cam_from_world = image.cam_from_world().matrix()
        rotation = cam_from_world[:, :3].T
        cameras[name] = model.cameras[image.camera_id]
        poses[name] = PosedPhoto(image.projection_center() * UNITS[units], rotation)
    if not poses:
        raise InputError(model_dir, "the COLMAP model holds no posed image")
    return cameras, poses


def pan_tilt_rotation(pan_deg: np.ndarray, tilt_deg: np.ndarray) -> np.ndarray:
    """(N, 3, 3) camera-to-world rotations of a camera held level (no roll) whose optical
    axis points at heading `pan_deg` (degrees counter-clockwise from +x, seen from above)
    and `tilt_deg` below the horizontal; z is up."""
    pan, tilt = np.radians(pan_deg), np.radians(tilt_deg)
    forward = np.stack([np.cos(tilt) * np.cos(pan), np.cos(tilt) * np.sin(pan),
                        -np.sin(tilt)], axis=-1)
    right = np.stack([np.sin(pan), -np.cos(pan), np.zeros_like(pan)], axis=-1)
    down = np.cross(forward, right)
    return np.stack([right, down, forward], axis=-1)


def read_pose_table(path: Path, units: str) -> dict[str, PosedPhoto]:
    """A rough-poses CSV (header `POSE_COLUMNS`): per photo file name, the camera centre
    (x, y, z in `units`, z up) and its heading (pan, degrees counter-clockwise from +x) and
    tilt (degrees below the horizontal), as a gantry logs them."""
    rows = read_csv_table(path, POSE_COLUMNS, "poses file")
    if not rows:
        raise InputError(path, "no rows: one row per photo")
    try:
        values = np.array([[float(row[c]) for c in POSE_COLUMNS[1:]] for row in rows])
    except KeyError as err:
        raise InputError(path, f"a row has no {err.args[0]}") from None
    except ValueError as err:
        raise InputError(path, f"a position or angle is not a number ({err})") from None
    if not np.isfinite(values).all():
        raise InputError(path, "a position or angle is not finite")
    names = [Path(row["file"]).name for row in rows]
    if len(set(names)) != len(names):
        raise InputError(path, "a photo is listed twice")
    rotations = pan_tilt_rotation(values[:, 3], values[:, 4])
    return {name: PosedPhoto(values[k, :3] * UNITS[units], rotations[k])
            for k, name in enumerate(names)}


def _undistorter(camera: pycolmap.Camera | None, width: int, height: int, max_size: int | None
                 ) -> tuple[Intrinsics, object]:
    """The pinhole camera the frames folder gets, and a function RGB -> RGB that makes an
    image of `camera` one of it (undistorted, then downscaled to `max_size`)."""
    from flowerpose.pipeline.undistort import Undistorter

    if camera is not None and (camera.width, camera.height) != (width, height):
        camera = pycolmap.Camera(camera.todict())  # a copy, at the photos' size
        camera.rescale(width, height)
    undistort = Undistorter(camera) if camera is not None and not camera.is_undistorted() \
        else None
    if undistort is not None:
        intrinsics = undistort.intrinsics
    elif camera is not None:
        intrinsics = Intrinsics(width, height, camera.focal_length_x, camera.focal_length_y,
                                camera.principal_point_x, camera.principal_point_y)
    else:
        intrinsics = Intrinsics(width, height, 1.0, 1.0, width / 2, height / 2)
    scale = 1.0 if not max_size else min(1.0, max_size / max(intrinsics.width,
                                                             intrinsics.height))
    target = (round(intrinsics.width * scale), round(intrinsics.height * scale))

    def convert(rgb: np.ndarray) -> np.ndarray:
        if undistort is not None:
            rgb = undistort(rgb)
        if scale < 1.0:
            rgb = cv2.resize(rgb, target, interpolation=cv2.INTER_AREA)
        return rgb

    return intrinsics.scaled(*target), convert


def _given_camera(names: list[str], colmap_cameras: dict[str, pycolmap.Camera],
                  calibration: pycolmap.Camera | None, where: Path) -> pycolmap.Camera | None:
    if calibration is not None:
        return calibration
    if not colmap_cameras:
        return None
    cameras = {colmap_cameras[n].camera_id for n in names if n in colmap_cameras}
    if len(cameras) > 1:
        raise InputError(where, f"the photos are of {len(cameras)} cameras in the model: a "
                         "frames folder holds one camera; import each camera's photos apart")
    return next(colmap_cameras[n] for n in names if n in colmap_cameras)


def _up_check_deg(poses: list[PosedPhoto]) -> float:
    """Degrees between +z and the cameras' mean image-up direction (-y): near 0 for a
    z-up frame filmed by an upright camera."""
    up = -np.mean([p.rotation[:, 1] for p in poses], axis=0)
    norm = np.linalg.norm(up)
    return float(np.degrees(np.arccos(np.clip(up[2] / norm, -1, 1)))) if norm > 1e-9 \
        else 180.0


def import_photos(source: Path, out_dir: Path, config: PhotoImportConfig = PhotoImportConfig(),
                  colmap: Path | None = None, calibration: Path | None = None,
                  poses: Path | None = None, overwrite: bool = False) -> dict:
    """Make a frames folder of photographs (a folder) or a video (a file); see the module.
    Returns frames.json's content. Every input is checked before anything is written."""
    if pycolmap is None:
        raise missing_extra("pycolmap", "flowerpose frames --images")
    source, out_dir = Path(source), Path(out_dir)
    watch = Stopwatch()
    if not source.exists():
        raise InputError(source, "not found: give a folder of photographs or a video file")
    if out_dir.resolve() == source.resolve() or source.resolve() in out_dir.resolve().parents:
        raise InputError(out_dir, "must not be the photos' folder or inside it")
    if (colmap or poses) and source.is_file():
        raise InputError(source, "poses (--colmap, --poses) name photographs; a video's frames "
                         "have no names: give the frames as photographs")
    if colmap and poses:
        raise InputError(poses, "give --colmap or --poses, not both")
    colmap_cameras, given = ({}, {})
    if colmap:
        colmap_cameras, given = read_colmap_model(colmap, config.units)
    elif poses:
        given = read_pose_table(poses, config.units)
    camera_file = read_camera_file(calibration) if calibration else None

    if source.is_dir():
        photos = list_photos(source)
        sizes = {p: image_size(p) for p in photos}
        if len(set(sizes.values())) > 1:
            first, odd = photos[0], next(p for p in photos if sizes[p] != sizes[photos[0]])
            raise InputError(odd, f"is {sizes[odd][0]}x{sizes[odd][1]} pixels, but "
                             f"{first.name} is {sizes[first][0]}x{sizes[first][1]}: one camera "
                             "at one resolution per frames folder")
        width, height = sizes[photos[0]]
        names = [p.name for p in photos]
        if given:
            missing = sorted(set(given) - set(names))
            if missing and colmap:
                raise InputError(colmap, f"names {len(missing)} images not in {source} "
                                 f"({', '.join(missing[:3])}{', ...' if len(missing) > 3 else ''})"
                                 ": the model is of other photographs")
            unposed = [n for n in names if n not in given]
            if unposed:
                raise InputError(poses or colmap, f"has no pose for {len(unposed)} of the "
                                 f"{len(names)} photos ({', '.join(unposed[:3])}"
                                 f"{', ...' if len(unposed) > 3 else ''})")
        frames_in: list[tuple[int, str, Path | np.ndarray]] = [
            (k, p.name, p) for k, p in enumerate(photos)]
    else:
        chosen = video_frames(source, FrameSelectConfig(count=config.count))
        height, width = chosen[0][1].shape[:2]
        frames_in = [(index, f"frame_{index:06d}.jpg", rgb) for index, rgb in chosen]
        names = [name for _, name, _ in frames_in]

    camera = _given_camera(names, colmap_cameras, camera_file, colmap or calibration)
    intrinsics, convert = _undistorter(camera, width, height, config.max_size)
    camera_source = "calibration" if camera_file else "colmap" if colmap else None
    if camera is None:
        focal = exif_focal_px(frames_in[0][2], width, height) \
            if isinstance(frames_in[0][2], Path) else None
        camera_source = "exif" if focal else "default"
        focal = focal or DEFAULT_FOCAL_FACTOR * max(width, height)
        scale = intrinsics.width / width
        intrinsics = Intrinsics(intrinsics.width, intrinsics.height, focal * scale,
                                focal * scale, intrinsics.width / 2, intrinsics.height / 2,
                                estimated=True)
    reencode = camera is not None and not camera.is_undistorted() or \
        (intrinsics.width, intrinsics.height) != (width, height)
    pose_kind = "calibrated" if colmap else "rough" if poses else "none"
    used = [given[n] for n in names] if given else []
    for n, pose in zip(names, used, strict=False):
        if not is_rotation(pose.rotation):
            raise InputError(colmap or poses, f"{n}: the pose's rotation is not a rotation")

    # Written beside out_dir and moved in only when whole: a failure (an image that does
    # not decode after its header read well, a full disk) leaves out_dir as it was.
    check_output(out_dir, "frames", overwrite, FRAMES_OUTPUTS)
    staging = staging_folder(out_dir)
    try:
        (staging / "frames").mkdir()
        entries = []
        with Tally(len(frames_in), "frames") as tally:
            for k, (index, name, image) in enumerate(frames_in):
                file = f"frames/{Path(name).stem}.jpg" if reencode or not isinstance(
                    image, Path) else f"frames/{name}"
                if isinstance(image, Path) and not reencode:
                    write_bytes(staging / file, image.read_bytes())
                else:
                    rgb = _read_rgb(image) if isinstance(image, Path) else image
                    write_image(staging / file, convert(rgb),
                                [cv2.IMWRITE_JPEG_QUALITY, config.jpeg_quality])
                entry = {"index": index, "file": file, "original": name}
                if used:
                    entry["pose"] = {"position": used[k].position.tolist(),
                                     "rotation": used[k].rotation.tolist()}
                entries.append(entry)
                tally.advance(1, f"frames: {k + 1}/{len(frames_in)} written"
                              if (k + 1) % 50 == 0 else None)
        camera_json = {**intrinsics.to_json(), "source": camera_source}
        if isinstance(frames_in[0][2], np.ndarray):
            capture = cv2.VideoCapture(str(source))
            camera_json["fps"] = float(capture.get(cv2.CAP_PROP_FPS) or 30.0)
            capture.release()
        write_json(staging / "camera.json", camera_json)
        result = {
            "source": str(source), "kind": "video" if source.is_file() else "photos",
            "poses": pose_kind,
            "pose_source": str(colmap or poses) if given else None,
            "pose_units": config.units if given else None,
            "camera": camera_source,
            "undistorted": bool(camera is not None and not camera.is_undistorted()),
            "up_check_deg": round(_up_check_deg(used), 2) if used else None,
            "config": {"count": config.count, "max_size": config.max_size,
                       "units": config.units},
            "seconds": round(watch.elapsed(), 3), "frames": entries}
        write_json(staging / "frames.json", result)
        publish(staging, out_dir, "frames", overwrite)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    if used and result["up_check_deg"] > 45:
        LOG.warning(f"note: {out_dir}: the given poses' frame is not z-up (the cameras' up is "
                    f"{result['up_check_deg']:.0f} degrees from +z): detect's 'flowers face "
                    "up' prior will mislead; reconstruct levels only pose-less photos")
    return result
