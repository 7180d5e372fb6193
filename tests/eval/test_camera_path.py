"""report.html draws the camera path a scanned plant's cloud was made from."""

import dataclasses

import numpy as np

from flowerpose.cloudio import Cloud, write_cloud
from flowerpose.eval.jobs.config import EvalConfig
from flowerpose.eval.jobs.plants import SyntheticJob, camera_path
from flowerpose.eval.reports.html_report import CAMERA_RAY_M, _view_3d, write_html_report
from flowerpose.jsonio import write_json


def _look_at(position, target):
    """(4, 4) camera-to-bed pose at `position` looking at `target` (OpenCV axes)."""
    z = np.asarray(target, float) - position
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = np.column_stack([x, np.cross(z, x), z]), position
    return pose


def _scanned_plant(plant_dir, poses):
    """An eval's plant folder as the scan source lays it out: the chosen frames
    (frames/frames.json with their poses, frames/*.jpg), the reconstructed cloud, the
    truth with the scan's visibility and the flowers found."""
    frames = []
    for k, pose in enumerate(poses):
        name = f"frames/frame_{10 * k:06d}.jpg"
        (plant_dir / "frames" / name).parent.mkdir(parents=True, exist_ok=True)
        (plant_dir / "frames" / name).write_bytes(b"\xff\xd8")
        frames.append({"index": 10 * k, "file": name, "bin": k,
                       "pose": {"position": pose[:3, 3].tolist(),
                                "rotation": pose[:3, :3].tolist()}})
    write_json(plant_dir / "frames" / "frames.json", {"frames": frames})
    rng = np.random.default_rng(0)
    write_cloud(plant_dir / "reconstruction" / "cloud.ply",
                Cloud(rng.random((200, 3)) * 0.2 + [1.4, 0.65, 0.0],
                      rng.integers(0, 255, (200, 3)).astype(np.uint8)))
    write_json(plant_dir / "scan" / "plant.json",
               {"seed": 0, "units": "m", "frame": "bed", "flowers": [
                   {"id": 0, "center": [1.5, 0.75, 0.2], "normal": [0, 0, 1], "radius": 0.013,
                    "petals": 5, "stage": "open", "visible": True}]})
    write_json(plant_dir / "flowers.json", {"units": "m", "frame": "bed", "flowers": []})


def test_a_scanned_plants_view_draws_its_kept_frames_in_order(tmp_path):
    centre = np.array([1.5, 0.75, 0.15])
    angles = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    poses = np.array([_look_at(centre + [0.3 * np.cos(a), 0.3 * np.sin(a), 0.1], centre)
                      for a in angles])
    out = tmp_path / "eval"
    plant_dir = out / "plants" / "seed-0"
    _scanned_plant(plant_dir, poses)
    np.testing.assert_allclose(camera_path(plant_dir, "scan"), poses, atol=1e-12)
    assert camera_path(plant_dir, "oracle") is None  # no camera made an oracle's cloud
    job = SyntheticJob("seed-0", plant_dir / "reconstruction" / "cloud.ply",
                       plant_dir / "scan" / "plant.json", "scan")
    view = job.view(EvalConfig(), out)
    traces = {trace.name: trace for trace in _view_3d(view).data}
    path = traces["camera path (6 frames)"]
    np.testing.assert_allclose(np.column_stack([path.x, path.y, path.z]), poses[:, :3, 3])
    # Each camera's ray runs from its centre along its viewing direction, towards the plant.
    ray = traces["viewing directions"]
    ends = np.column_stack([np.array(v, dtype=float) for v in (ray.x, ray.y, ray.z)])
    starts, tips = ends[0::3], ends[1::3]
    np.testing.assert_allclose(starts, poses[:, :3, 3])
    np.testing.assert_allclose(tips - starts, CAMERA_RAY_M * poses[:, :3, 2], atol=1e-12)
    assert np.all(np.linalg.norm(tips - centre, axis=1) < np.linalg.norm(starts - centre, axis=1))
    page = write_html_report(tmp_path / "report.html", "scan", None, [view])
    assert "camera path (6 frames)" in page.read_text()
    oracle_view = dataclasses.replace(job, source="oracle").view(EvalConfig(), out)
    assert not any("camera" in (t.name or "") for t in _view_3d(oracle_view).data)
