"""The printed ChArUco board: found in an image, its corners triangulated, and photos of a
scene with one beside it, taken round with no poses and no calibration, reconstructed metric
and upright."""

import cv2  # noqa: F401  # before pycolmap (pipeline/sfm.py)
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from flowerpose.errors import InputError
from flowerpose.pipeline.align import Similarity, umeyama
from flowerpose.pipeline.board import (
    BoardSpec,
    board_image,
    board_similarity,
    find_corners,
    triangulate,
)
from flowerpose.pipeline.photos import import_photos, pan_tilt_rotation
from flowerpose.pipeline.reconstruct import reconstruct
from tests.cli_run import run_cli

SPEC = BoardSpec()


def test_the_printed_board_prints_to_size_and_its_corners_are_found(tmp_path, capsys):
    image = board_image(SPEC, dpi=150)
    square_px = SPEC.square_m / 0.0254 * 150
    assert image.shape[1] == pytest.approx(SPEC.squares_x * square_px + 2 * 0.01 / 0.0254 * 150,
                                           abs=2)
    ids, pixels = find_corners(image, SPEC)
    assert sorted(ids) == list(range((SPEC.squares_x - 1) * (SPEC.squares_y - 1)))
    # Neighbouring corners one square apart.
    order = np.argsort(ids)
    step = np.linalg.norm(np.diff(pixels[order][:SPEC.squares_x - 1], axis=0), axis=1)
    assert np.allclose(step, square_px, rtol=0.01)
    code, out, _ = run_cli(capsys, "marker", "--out", tmp_path / "board.pdf")
    assert code == 0 and (tmp_path / "board.pdf").read_bytes().startswith(b"%PDF")
    code, _, err = run_cli(capsys, "marker", "--out", tmp_path / "board.svg")
    assert code == 2 and ".png or .pdf" in err


def _view(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(3, 4) cam_from_world of a level camera at `centre` looking at `target`."""
    forward = target - centre
    pan = np.degrees(np.arctan2(forward[1], forward[0]))
    tilt = np.degrees(np.arctan2(-forward[2], np.linalg.norm(forward[:2])))
    rotation = pan_tilt_rotation(np.array([pan]), np.array([tilt]))[0]
    return np.c_[rotation.T, -rotation.T @ centre]


def test_board_corners_seen_from_cameras_give_the_scale_and_up_back():
    corners = SPEC.corners()
    # The board lies face up at the origin of a world whose unit is 1/4 metre, turned.
    # (OpenCV's board frame has z into the printed face: face up is z down.)
    turn = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    truth = Similarity(4.0, turn @ np.diag([1.0, -1.0, -1.0]), np.array([1.0, 2.0, 0.0]))
    world = truth.apply(corners - corners.mean(axis=0))
    centres = [4 * np.array([0.3 * np.cos(a), 0.3 * np.sin(a), 0.25]) + [1, 2, 0]
               for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    observations = {}
    for centre in centres:
        view = _view(np.asarray(centre), np.array([1.0, 2.0, 0.0]))
        in_camera = world @ view[:, :3].T + view[:, 3]
        for k, point in enumerate(in_camera):
            observations.setdefault(k, []).append((point[:2] / point[2], view))
    assert np.allclose(triangulate([r for r, _ in observations[5]],
                                   [v for _, v in observations[5]]), world[5])
    similarity, fit = board_similarity(observations, np.array(centres), SPEC)
    assert similarity.scale == pytest.approx(0.25)
    assert fit["rms_m"] < 1e-9 and fit["corners"] == len(corners)
    placed = similarity.apply(np.array(centres))
    assert np.all(placed[:, 2] > 0)  # the cameras above the board, z up
    assert np.allclose(placed[:, 2], 0.25)
    with pytest.raises(InputError, match="behind the board"):
        board_similarity(observations, -np.array(centres) + [2, 4, 0], SPEC)
    with pytest.raises(InputError, match="need 6"):
        board_similarity({k: observations[k] for k in range(3)}, np.array(centres), SPEC)


def _render(view: np.ndarray, focal: float, size: tuple[int, int], textures: dict,
            boxes: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """An RGB photo of the scene: a textured ground (z = 0) with the board printed on it
    face up at the origin, and textured boxes standing on it; a pinhole camera, 2 x 2
    supersampled."""
    width, height = size
    ss = 2
    u, v = np.meshgrid((np.arange(width * ss) + 0.5) / ss, (np.arange(height * ss) + 0.5) / ss)
    rays_cam = np.stack([(u - width / 2) / focal, (v - height / 2) / focal,
                         np.ones_like(u)], axis=-1).reshape(-1, 3)
    rotation = view[:, :3].T
    origin = -rotation @ view[:, 3]
    rays = rays_cam @ rotation.T
    depth = np.full(len(rays), np.inf)
    hit_kind = np.zeros(len(rays), np.int8)  # 0 sky, 1 ground, 2.. box faces
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = -origin[2] / rays[:, 2]
    ground = (t_ground > 0)
    depth[ground] = t_ground[ground]
    hit_kind[ground] = 1
    face_axis = np.zeros(len(rays), np.int8)
    for low, high in boxes:
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (low - origin) / rays, (high - origin) / rays
        near = np.minimum(t1, t2)
        entry, leave = near.max(axis=1), np.maximum(t1, t2).min(axis=1)
        hit = (entry <= leave) & (entry > 0) & (entry < depth)
        depth[hit] = entry[hit]
        hit_kind[hit] = 2
        face_axis[hit] = near[hit].argmax(axis=1)
    points = origin + rays * np.where(np.isfinite(depth), depth, 0)[:, None]
    colour = np.zeros((len(rays), 3))
    texture, texel = textures["noise"], textures["texel_m"]

    def lookup(a, b):
        rows = np.mod(np.floor(b / texel).astype(np.int64), texture.shape[0])
        cols = np.mod(np.floor(a / texel).astype(np.int64), texture.shape[1])
        return texture[rows, cols]

    on_ground = hit_kind == 1
    colour[on_ground] = lookup(points[on_ground, 0], points[on_ground, 1])
    board, px_per_m = textures["board"], textures["board_px_per_m"]
    col = (points[:, 0] + board.shape[1] / px_per_m / 2) * px_per_m
    row = (board.shape[0] / px_per_m / 2 - points[:, 1]) * px_per_m
    on_board = on_ground & (col >= 0) & (col < board.shape[1] - 1) & (row >= 0) & (
        row < board.shape[0] - 1)
    colour[on_board] = board[row[on_board].astype(int), col[on_board].astype(int)][:, None]
    for axis in range(3):
        face = (hit_kind == 2) & (face_axis == axis)
        a, b = [k for k in range(3) if k != axis]
        colour[face] = lookup(points[face, a] + 0.37 * axis, points[face, b] + 0.11 * axis)
    colour[hit_kind == 0] = (200, 210, 225)
    image = colour.reshape(height * ss, width * ss, 3).astype(np.float32)
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA).clip(0, 255).astype(np.uint8)


@pytest.mark.slow
def test_photos_with_a_board_and_no_poses_give_a_metric_upright_cloud(tmp_path, capsys):
    rng = np.random.default_rng(7)
    noise = cv2.resize(rng.integers(0, 256, (128, 128, 3)).astype(np.float32), (512, 512),
                       interpolation=cv2.INTER_CUBIC)
    textures = {"noise": noise.clip(0, 255), "texel_m": 0.0015,
                "board": board_image(SPEC, dpi=254), "board_px_per_m": 10000.0}
    # Boxes standing round the board: the scene a plant and its pot would be.
    boxes = [(np.array([x, y, 0.0]), np.array([x + 0.05, y + 0.06, h]))
             for x, y, h in ((0.13, -0.05, 0.12), (-0.2, 0.02, 0.08), (0.0, 0.12, 0.15),
                             (-0.05, -0.2, 0.1))]
    photos = tmp_path / "photos"
    photos.mkdir()
    focal, size = 420.0, (512, 384)
    centres = []
    for k, angle in enumerate(np.linspace(0, 2 * np.pi, 20, endpoint=False)):
        height = 0.28 if k % 2 else 0.22
        centre = np.array([0.42 * np.cos(angle), 0.42 * np.sin(angle), height])
        centres.append(centre)
        rgb = _render(_view(centre, np.array([0.0, 0.0, 0.03])), focal, size, textures, boxes)
        cv2.imwrite(str(photos / f"photo{k:02d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    import_photos(photos, tmp_path / "frames")
    result = reconstruct(tmp_path / "frames", tmp_path / "recon", progress=False)
    sparse = result.report["sparse"]
    assert sparse["alignment"]["kind"] == "board" and result.report["metric"]
    assert sparse["alignment"]["board"]["corners"] >= 18
    found = {image.name: image.projection_center()
             for image in result.sparse.reconstruction.images.values() if image.has_pose}
    names = sorted(found)
    truth = np.array([centres[int(n.split("photo")[1][:2])] for n in names])
    similarity = umeyama(np.array([found[n] for n in names]), truth)
    assert len(names) >= 19
    assert similarity.scale == pytest.approx(1.0, abs=0.01)  # metric within 1 %
    up = similarity.rotation @ np.array([0, 0, 1.0])
    assert np.degrees(np.arccos(np.clip(up[2], -1, 1))) < 1.0  # z up
    # z = 0 on the board: the cameras' heights come back.
    heights = np.array([found[n][2] for n in names])
    assert np.allclose(heights, truth[:, 2], atol=0.005)
    assert isinstance(result.sparse.reconstruction, pycolmap.Reconstruction)
    # Another board required (other markers): not found, one line, nothing written.
    capsys.readouterr()  # what the run above logged
    code, _, err = run_cli(capsys, "reconstruct", "-q", tmp_path / "frames", "--out",
                           tmp_path / "other", "--set", "scan.reconstruct.sfm.board=required",
                           "--set", "scan.reconstruct.sfm.board_spec.dictionary=DICT_4X4_50")
    assert code == 2 and "no 7 x 5 ChArUco board (DICT_4X4_50) found" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "other").exists()
