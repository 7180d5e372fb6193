"""Camera rendering against ray-cast truth: depth, instance masks, the camera conventions."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest
from simhelpers import box, cached_plant, handmade_plant

from flowerpose.jsonio import write_json
from flowerpose.scanio import read_intrinsics
from flowerpose.sim.camera import (
    CameraConfig,
    intrinsics_from_config,
    intrinsics_from_json,
    look_at,
    opencv_to_opengl,
    pose_matrix,
    project,
    unproject,
)
from flowerpose.sim.pieces import Part, Piece
from flowerpose.sim.plant_colours import rgba8
from flowerpose.sim.raycast import make_scene
from flowerpose.sim.render import Output, PlantRenderer, RenderConfig
from flowerpose.sim.shapes import grid_faces

SMALL = intrinsics_from_config().scaled(320, 180)
NO_GROUND = RenderConfig(ground_margin_m=None)


@pytest.fixture(scope="module")
def seed0():
    plant = cached_plant(0, "realistic")
    with PlantRenderer(plant, NO_GROUND) as renderer:
        yield plant, renderer


def pixel_rays(camera_to_bed, intrinsics):
    """Ray-casting rays through every pixel centre, (H * W, 6), direction z = 1 in the
    camera frame (so the hit distance is the depth along the optical axis)."""
    v, u = np.mgrid[:intrinsics.height, :intrinsics.width]
    uv = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1)
    ends = unproject(uv, np.ones(len(uv)), camera_to_bed, intrinsics)
    origin = np.broadcast_to(camera_to_bed[:3, 3], ends.shape)
    return np.concatenate([origin, ends - origin], 1).astype(np.float32)


def cast(plant, camera_to_bed, intrinsics):
    """Depth (H, W) (inf where no hit) and the hit face (H, W) (-1 where none) of every
    pixel centre."""
    scene = make_scene(plant.mesh.vertices, plant.mesh.faces)
    hits = scene.cast_rays(o3d.core.Tensor(pixel_rays(camera_to_bed, intrinsics)))
    shape = (intrinsics.height, intrinsics.width)
    depth = hits["t_hit"].numpy().reshape(shape)
    face = hits["primitive_ids"].numpy().astype(np.int64).reshape(shape)
    return depth, np.where(np.isfinite(depth), face, -1)


def side_view(plant, distance=0.5):
    """A camera `distance` from the plant axis at half its height, looking at the middle
    of the leaf triangle nearest the axis there (so the optical axis meets the plant)."""
    center = plant.center + [0.0, 0.0, 0.5 * plant.height]
    leaf = plant.mesh.vertices[plant.mesh.faces[plant.face_part == Part.LEAF]].mean(1)
    target = leaf[np.argmin(np.linalg.norm(leaf - center, axis=1))]
    return look_at(target + [distance, 0.0, 0.0], target)


def test_depth_equals_ray_cast_distance(seed0):
    plant, renderer = seed0
    pose = side_view(plant)
    # An odd size puts the centre pixel's centre on the principal point (the optical axis).
    odd = intrinsics_from_config().scaled(321, 181)
    out = renderer.render(pose, odd)
    truth, _ = cast(plant, pose, odd)
    seen = out.depth > 0
    assert out.rgb.shape == (181, 321, 3) and out.rgb.dtype == np.uint8
    assert out.depth.dtype == np.float32
    assert 0.1 < seen.mean() < 0.9, "the plant fills part of the view"
    assert out.rgb[seen].std() > 20, "the plant is not a flat colour"
    background = np.all(out.rgb == RenderConfig().background_rgb, axis=2)
    assert background[~seen].mean() > 0.97, "anti-aliased edges aside"
    assert (seen == np.isfinite(truth)).mean() > 0.999
    both = seen & np.isfinite(truth)
    assert (np.abs(out.depth - truth)[both] < 1e-3).mean() > 0.999
    row, col = odd.height // 2, odd.width // 2
    assert (col + 0.5, row + 0.5) == (odd.cx, odd.cy)
    assert np.isfinite(truth[row, col])
    assert abs(out.depth[row, col] - truth[row, col]) < 1e-3


def test_instance_masks_equal_ray_cast_flowers(seed0):
    plant, renderer = seed0
    pose = look_at(plant.center + [0.25, -0.3, plant.height + 0.2],
                   plant.center + [0.0, 0.0, 0.6 * plant.height])
    out = renderer.render(pose, SMALL, Output.INSTANCE)
    _, face = cast(plant, pose, SMALL)
    truth = np.where(face >= 0, plant.face_flower[np.maximum(face, 0)], -1)
    assert out.rgb is None and out.depth is None
    assert len(np.unique(truth[truth >= 0])) >= 3
    assert (out.instance == truth).mean() > 0.998


def test_flower_centre_projects_into_its_mask(seed0):
    plant, renderer = seed0
    scene = make_scene(plant.mesh.vertices, plant.mesh.faces)
    checked = 0
    for flower in plant.flowers:
        side = np.cross(flower.normal, [0.0, 0.0, 1.0])
        side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-6 else np.array(
            [1.0, 0, 0])
        # Facing the flower, the view aimed beside it: the flower lands off the image centre.
        eye = flower.center + 0.25 * flower.normal
        pose = look_at(eye, flower.center + 0.04 * side)
        ray = np.concatenate([eye, flower.center - eye])[None].astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(ray))
        first = int(hit["primitive_ids"].numpy()[0])
        if not np.isfinite(hit["t_hit"].numpy()[0]) or plant.face_flower[first] != flower.id:
            continue  # another flower or a leaf is in front of it
        uv, depth = project(flower.center[None], pose, SMALL)
        col, row = np.floor(uv[0]).astype(int)
        assert depth[0] > 0 and abs(col - SMALL.width / 2) > 10
        instance = renderer.render(pose, SMALL, Output.INSTANCE).instance
        assert instance[row, col] == renderer.instance_id(0, flower.id)
        checked += 1
    assert checked >= 3


def test_default_intrinsics_and_json_round_trip(tmp_path):
    config = CameraConfig()
    k = intrinsics_from_config(config)
    assert (k.width, k.height, k.fps) == (1280, 720, 30.0)
    assert k.fx == pytest.approx(640 / math.tan(math.radians(31.1)))
    assert k.fy == k.fx and (k.cx, k.cy) == (640.0, 360.0)
    assert config.vfov_deg == pytest.approx(37.5, abs=0.1)
    data = k.to_json()
    assert data["model"] == "PINHOLE"
    assert intrinsics_from_json(data) == k
    assert read_intrinsics(write_json(tmp_path / "camera.json", data)) == k
    half = k.scaled(640, 360)
    assert (half.fx, half.cx, half.cy) == pytest.approx((k.fx / 2, 320.0, 180.0))
    shifted = intrinsics_from_config(CameraConfig(principal_point=(630.5, 355.0)))
    assert (shifted.cx, shifted.cy) == (630.5, 355.0)


def test_projection_and_pose_conventions():
    pose = look_at([0.0, 0.0, 0.3], [1.0, 0.0, 0.3])
    # Looking along +x with +z up: the image's right is -y, its bottom -z.
    assert np.allclose(pose[:3, :3], [[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    assert np.allclose(opencv_to_opengl(pose)[:3, 2], [-1, 0, 0]), "OpenGL looks along -z"
    assert np.allclose(opencv_to_opengl(opencv_to_opengl(pose)), pose)
    k = intrinsics_from_config()
    uv, depth = project(np.array([[0.5, 0.1, 0.35], [0.5, 0.0, 0.3]]), pose, k)
    assert np.allclose(uv[1], [k.cx, k.cy]) and np.allclose(depth, 0.5)
    assert uv[0, 0] < k.cx and uv[0, 1] < k.cy, "left (+y) and up (+z): upper left"
    assert np.allclose(unproject(uv, depth, pose, k), [[0.5, 0.1, 0.35], [0.5, 0.0, 0.3]])
    down = look_at([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    assert np.allclose(down[:3, 0], [0, -1, 0]) and np.allclose(down[:3, 2], [0, 0, -1])
    assert np.allclose(pose_matrix(pose[:3, 3], pose[:3, :3]), pose)


def test_small_box_renders_where_it_projects():
    point = np.array([1.5, 0.55, 0.42])
    # A 1 mm plate facing the camera: its sides hardly show, its face centres on `point`.
    plant = handmade_plant([], [box(point + [0.0005, 0, 0], [0.001, 0.01, 0.01])])
    pose = look_at([1.0, 0.75, 0.3], [1.5, 0.75, 0.3])
    with PlantRenderer(plant, NO_GROUND) as renderer:
        depth = renderer.render(pose, SMALL, Output.DEPTH).depth
    rows, cols = np.nonzero(depth > 0)
    uv, z = project(point[None], pose, SMALL)
    assert len(rows) > 10
    # The box's visible face is nearly centred on its centre's projection (a pixel or so).
    assert np.allclose([cols.mean() + 0.5, rows.mean() + 0.5], uv[0], atol=1.0)
    assert uv[0, 0] > SMALL.cx and uv[0, 1] < SMALL.cy, "right (-y) and up (+z)"
    assert abs(np.median(depth[rows, cols]) - z[0]) < 1e-3


def test_instances_of_several_plants():
    up = np.array([0.0, 0.0, 1.0])
    a = handmade_plant([(np.array([1.0, 0.7, 0.1]), up), (np.array([1.06, 0.7, 0.1]), up)], [])
    b = handmade_plant([(np.array([1.0, 0.8, 0.1]), up), (np.array([1.06, 0.8, 0.1]), up)], [])
    with PlantRenderer([a, b], RenderConfig(ground_margin_m=0.3)) as renderer:
        assert [renderer.instance_id(p, f) for p in (0, 1) for f in (0, 1)] == [0, 1, 2, 3]
        assert renderer.flower_of(3) == (1, 1) and renderer.flower_of(0) == (0, 0)
        out = renderer.render(look_at([1.03, 0.75, 0.4], [1.03, 0.75, 0.1]), SMALL)
    assert set(np.unique(out.instance)) == {-1, 0, 1, 2, 3}
    assert np.all(out.depth > 0), "the ground fills the view around the flowers"


def test_sun_casts_shadows_and_close_is_safe():
    # Light is baked per vertex: the soil needs vertices where the shadow falls.
    u, v = np.meshgrid(np.linspace(1.3, 1.7, 81), np.linspace(0.55, 0.95, 81), indexing="ij")
    grid = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], 1)
    soil = Piece.of(grid, grid_faces(81, 81), rgba8(np.full((len(grid), 3), 0.4)), Part.SOIL)
    blocker = box([1.5, 0.75, 0.06], [0.03, 0.03, 0.01])
    plant = handmade_plant([], [soil, blocker])
    config = RenderConfig(sun_elevation_deg=45.0, sun_azimuth_deg=0.0, ground_margin_m=None)
    renderer = PlantRenderer(plant, config)
    pose = look_at([1.5, 0.75, 0.5], [1.5, 0.75, 0.0])
    rgb = renderer.render(pose, SMALL, Output.RGB).rgb
    # The sun shines from +x at 45 degrees: the blocker's shadow lies 6 cm toward -x.
    (shadow, lit), _ = project(np.array([[1.44, 0.75, 0.0], [1.56, 0.75, 0.0]]), pose, SMALL)
    brightness = [rgb[int(v), int(u)].astype(float).sum() for u, v in (shadow, lit)]
    assert brightness[0] < 0.75 * brightness[1]
    renderer.close()
    renderer.close()
    with pytest.raises(RuntimeError):
        renderer.render(pose, SMALL)


@pytest.mark.slow
def test_renders_alongside_mujoco():
    mujoco = pytest.importorskip("mujoco")
    model = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><light pos="0 0 3"/><camera name="top" pos="0 0 1"/>'
        '<geom type="box" size=".2 .2 .05" rgba="1 0 0 1"/></worldbody></mujoco>')
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    try:
        theirs = mujoco.Renderer(model, 64, 64)
    except Exception as error:  # MuJoCo bound to a display-less GL (set MUJOCO_GL=egl)
        pytest.skip(f"no MuJoCo rendering here: {error}")
    plant = handmade_plant([], [box([1.5, 0.75, 0.3], [0.05, 0.05, 0.05])])
    pose = look_at([1.5, 0.75, 0.6], [1.5, 0.75, 0.3])
    with theirs, PlantRenderer(plant, NO_GROUND) as ours:
        for _ in range(2):  # each renderer keeps working after the other has rendered
            theirs.update_scene(data, camera="top")
            red = theirs.render()[32, 32]
            assert red[0] > int(red[1]) + 60 and red[0] > int(red[2]) + 60
            depth = ours.render(pose, SMALL, Output.DEPTH).depth
            assert depth[90, 160] == pytest.approx(0.275, abs=1e-3)
    with mujoco.Renderer(model, 64, 64) as again, PlantRenderer(plant, NO_GROUND) as fresh:
        again.update_scene(data, camera="top")
        assert again.render()[32, 32, 0] > 100
        depth = fresh.render(pose, SMALL, Output.DEPTH).depth
        assert depth[90, 160] == pytest.approx(0.275, abs=1e-3)
