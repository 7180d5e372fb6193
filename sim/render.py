"""Camera rendering of synthetic plants with pyrender: RGB, depth and per-flower instances.

One `PlantRenderer` holds one pyrender scene of one or more plants (already placed in the
bed frame) and an optional soil ground around them. `render` takes a camera pose in the
project's convention (OpenCV axes, `flowerpose.sim.camera`) and intrinsics in pixels.

Lighting is baked into the vertex colours once, when the renderer is built, because the
scene never moves and Lambertian light does not depend on the view: a sun and a weaker
fill from the other side, each shadowed (a few rays per vertex toward a slightly soft
light), plus sky light scaled by how much of the sky each surface sees (ambient
occlusion) and a little light bounced from the ground and leaves. Leaves and petals are
open sheets, so each side of a sheet is lit on its own, and thin petals and leaves pass
some light through to their shaded side. The render pass then only interpolates colours
(pyrender's FLAT mode): shadows, occlusion darkening and translucent petals for less than
the cost of an unlit render (here 0.06-0.09 s a 1280 x 720 frame, where pyrender's own
lights with shadow maps took 1 s and left shadow acne on the leaves). What this leaves
out: specular highlights, and shading detail finer than the mesh's vertices.

Headless rendering uses EGL (Mesa llvmpipe on CPU): this module sets
`PYOPENGL_PLATFORM=egl` and `MUJOCO_GL=egl` unless they are set, so import it before
anything that imports OpenGL. All renderers of the process share one pyrender
`OffscreenRenderer` (resized to each request) that is never deleted: pyrender's
`delete()` terminates the EGL display that MuJoCo's renderer shares, and a pyrender mesh
can be bound to one GL context only.
"""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("MUJOCO_GL", "egl")

import atexit  # noqa: E402
import math  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from enum import IntFlag  # noqa: E402

import numpy as np  # noqa: E402
import OpenGL.error  # noqa: E402
import pyrender  # noqa: E402

from flowerpose.errors import InputError  # noqa: E402
from flowerpose.log import open3d  # noqa: E402
from flowerpose.memory import require_fits  # noqa: E402
from flowerpose.sim import plant_colours as colours  # noqa: E402
from flowerpose.sim.camera import (  # noqa: E402
    MAX_RENDER_SIDE,
    CameraConfig,
    Intrinsics,
    opencv_to_opengl,
)
from flowerpose.sim.pieces import Part  # noqa: E402
from flowerpose.sim.plant import Plant  # noqa: E402
from flowerpose.sim.raycast import make_scene  # noqa: E402
from flowerpose.sim.render_config import RenderConfig  # noqa: E402
from flowerpose.sim.shapes import grid_faces  # noqa: E402
from flowerpose.srgb import linear_to_srgb, srgb_to_linear  # noqa: E402

o3d = open3d()

TRANSLUCENCY = {Part.PETAL: 0.35, Part.LEAF: 0.12, Part.SEPAL: 0.08}
"""Share of the light on one side of a thin part that its other side shows (other parts:
0). Strawberry petals are thin and glow when lit from behind; leaves pass a little green."""

_GROUND_SPACING_M = 0.02
"""Vertex spacing of the ground grid, metres (its colour patches and shadows)."""
_LIGHTING_SEED = 20240229
"""Seed of the ground's colour pattern and of the lighting rays' jitter: the scenery and
its light are the same every time and belong to no plant's truth."""
_RAY_OFFSET_M = 2e-4
"""Lighting rays start this far off the surface, metres, so they do not hit it."""


class Output(IntFlag):
    """Images `PlantRenderer.render` makes: RGB costs one render pass, DEPTH and
    INSTANCE together another (about as long)."""

    RGB = 1
    DEPTH = 2
    INSTANCE = 4
    ALL = 7


@dataclass(frozen=True)
class RenderOutput:
    """What the camera sees from one pose; an image not asked for is None."""

    rgb: np.ndarray | None
    """(H, W, 3) uint8, RGB."""
    depth: np.ndarray | None
    """(H, W) float32, metres along the optical axis (camera z) of the surface at each
    pixel's centre, 0 where no surface is seen (the common RGB-D convention for "no
    measurement")."""
    instance: np.ndarray | None
    """(H, W) int32 open-flower instance seen at each pixel's centre (its petal,
    receptacle, stamen or sepal), -1 elsewhere; see `PlantRenderer.instance_id`."""


_shared: pyrender.OffscreenRenderer | None = None


#: Bytes a rendered pixel takes while a frame is made: the framebuffer's colour, depth and
#: segmentation passes, the RGB, depth and instance images, and the sensor model's float
#: copies of the image.
RENDER_BYTES_PER_PIXEL = 4 + 4 + 4 + 3 + 4 + 4 + 3 * 12


def _offscreen(width: int, height: int) -> pyrender.OffscreenRenderer:
    """The process's one OffscreenRenderer, sized width x height (checked first: a size
    OpenGL or this machine cannot take is one line naming the camera's settings)."""
    setting = "scan.camera.width and scan.camera.height"
    if max(width, height) > MAX_RENDER_SIDE:
        raise InputError(setting, f"a {width}x{height} image is larger than OpenGL renders "
                         f"({MAX_RENDER_SIDE} pixels a side); use a smaller camera image")
    require_fits(width * height * RENDER_BYTES_PER_PIXEL, setting,
                 f"rendering a {width}x{height} image", opencv_array=width * height * 12)
    global _shared
    if _shared is None:
        _shared = pyrender.OffscreenRenderer(width, height)
        atexit.register(_forget_at_exit)
    else:
        _shared.viewport_width, _shared.viewport_height = width, height
    return _shared


def _forget_at_exit() -> None:
    """Free the shared renderer's GL objects while Python still can, and stop its
    finaliser from running at shutdown, where it would terminate the EGL display and fail
    noisily. Process exit reclaims the context itself."""
    if _shared is None or _shared._renderer is None:
        return
    try:
        _shared._platform.make_current()
        _shared._renderer.delete()
    except (AssertionError, OpenGL.error.Error):
        pass  # MuJoCo's exit handler may have terminated the shared display already
    _shared._renderer = None
    _shared._platform = None


def _direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """(3,) unit vector toward a light at this elevation and azimuth, bed frame."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def _tangents(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two (N, 3) unit vectors completing (N, 3) unit normals to right-handed frames."""
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(normals, t1)


def _triangle_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) normals of triangles by their winding, length twice their area."""
    tri = vertices[faces]
    return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])


def _unit(v: np.ndarray) -> np.ndarray:
    """Rows of (N, 3) scaled to unit length (zero rows stay zero)."""
    length = np.linalg.norm(v, axis=1, keepdims=True)
    return np.divide(v, length, out=np.zeros_like(v), where=length > 0)


class _Lighting:
    """Baked light: what each side of a surface point receives, as a share of its colour."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, config: RenderConfig):
        """vertices (V, 3) metres and faces (F, 3) of the surfaces that cast shadows."""
        self.config = config
        self.rng = np.random.default_rng(_LIGHTING_SEED)
        self.scene = make_scene(vertices, faces) if config.shadows else None

    def _open(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """(R,) bool: the ray from each origin along its direction ((R, 3) each) hits
        nothing."""
        rays = np.concatenate([origins, directions], 1).astype(np.float32)
        hit = self.scene.test_occlusions(o3d.core.Tensor(rays)).numpy()
        return ~hit.astype(bool)

    def _light(self, points: np.ndarray, normals: np.ndarray, toward: np.ndarray,
               softness_deg: float, rays: int) -> tuple[np.ndarray, np.ndarray]:
        """(N,) cosine and visibility of a directional light for the side of each point
        that faces it (points, unit normals (N, 3); toward (3,) unit)."""
        cosine = normals @ toward
        if self.scene is None:
            return cosine, np.ones(len(points))
        side = np.where(cosine >= 0, 1.0, -1.0)[:, None] * normals
        spread = math.radians(softness_deg)
        t1, t2 = _tangents(np.tile(toward, (len(points), 1)))
        radius = spread * np.sqrt(self.rng.uniform(size=(len(points), rays, 1)))
        angle = self.rng.uniform(0, 2 * np.pi, (len(points), rays, 1))
        directions = (toward + radius * (np.cos(angle) * t1[:, None]
                                         + np.sin(angle) * t2[:, None]))
        origins = np.repeat(points + _RAY_OFFSET_M * side, rays, axis=0)
        seen = self._open(origins, directions.reshape(-1, 3)).reshape(len(points), rays)
        return cosine, seen.mean(1)

    def _sky(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(N,) share of the cosine-weighted hemisphere over each (point, unit normal)
        that is open sky (unblocked and above the horizon)."""
        if self.scene is None:
            return np.clip(0.5 + 0.5 * normals[:, 2], 0.0, 1.0)
        k = self.config.sky_rays
        # A cosine-weighted spiral of directions, turned by a random angle at each point.
        radius = np.sqrt((np.arange(k) + 0.5) / k)
        angle = np.arange(k) * math.pi * (3 - math.sqrt(5))
        angle = angle[None] + self.rng.uniform(0, 2 * np.pi, (len(points), 1))
        t1, t2 = _tangents(normals)
        up = np.sqrt(1 - radius ** 2)[None, :, None]
        directions = ((radius * np.cos(angle))[..., None] * t1[:, None]
                      + (radius * np.sin(angle))[..., None] * t2[:, None] + up * normals[:, None])
        origins = np.repeat(points + _RAY_OFFSET_M * normals, k, axis=0)
        flat = directions.reshape(-1, 3)
        sky = self._open(origins, flat) & (flat[:, 2] > 0)
        return sky.reshape(len(points), k).mean(1)

    def colors(self, points: np.ndarray, normals: np.ndarray, albedo: np.ndarray,
               translucency: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """sRGB colours in [0, 1] ((N, 3) each) of the front (along the normal) and back
        sides of surface points.

        points (N, 3) metres; normals (N, 3) unit (zero for a vertex of no triangle); albedo
        (N, 3) linear RGB; translucency (N,) share passed to the other side.
        """
        cfg = self.config
        tint = np.asarray(cfg.sky_tint)
        # Vertices of no triangle have no normal: any will do.
        normals = np.where(np.linalg.norm(normals, axis=1, keepdims=True) > 0, normals,
                           [[0.0, 0.0, 1.0]])
        direct = np.zeros((2, len(points), 3))
        for level, toward, tint_of, rays in (
                (cfg.sun, _direction(cfg.sun_elevation_deg, cfg.sun_azimuth_deg), np.ones(3), 4),
                (cfg.fill, _direction(cfg.fill_elevation_deg, cfg.sun_azimuth_deg + 180.0),
                 tint, 2)):
            cosine, visible = self._light(points, normals, toward, cfg.sun_softness_deg, rays)
            lit = level * np.abs(cosine) * visible
            facing = cosine >= 0
            # The side facing the light gets it; the other side what passes through.
            direct[0] += np.where(facing, 1.0, translucency)[:, None] * lit[:, None] * tint_of
            direct[1] += np.where(facing, translucency, 1.0)[:, None] * lit[:, None] * tint_of
        out = []
        for side in (0, 1):
            sky = self._sky(points, normals if side == 0 else -normals)
            ambient = cfg.sky * sky[:, None] * tint + cfg.bounce * (1 - sky)[:, None]
            out.append(linear_to_srgb(albedo * (direct[side] + ambient)))
        return out[0], out[1]


def _ground(bounds: np.ndarray, margin: float, z: float) -> tuple[np.ndarray, np.ndarray,
                                                                   np.ndarray]:
    """Vertices (V, 3), faces (F, 3) and RGBA uint8 colours (V, 4) of a patchy soil
    rectangle `margin` metres beyond the xy `bounds` ((2, 3) min and max corners)."""
    lo, hi = bounds[0, :2] - margin, bounds[1, :2] + margin
    nu, nv = (np.ceil((hi - lo) / _GROUND_SPACING_M).astype(int) + 1)
    u, v = np.meshgrid(np.linspace(lo[0], hi[0], nu), np.linspace(lo[1], hi[1], nv),
                       indexing="ij")
    xy = np.stack([u.ravel(), v.ravel()], 1)
    rng = np.random.default_rng(_LIGHTING_SEED)
    count = 8
    angle = rng.uniform(0, 2 * np.pi, count)
    wavenumber = 2 * np.pi / rng.uniform(0.05, 0.4, count)
    vectors = np.stack([np.cos(angle), np.sin(angle)], 1) * wavenumber[:, None]
    waves = np.sin(xy @ vectors.T + rng.uniform(0, 2 * np.pi, count)).sum(1)
    waves /= np.sqrt(0.5 * count)
    shift = np.stack([2.0 * waves, 0.03 * waves, -0.04 * waves], 1)
    rgba = colours.tone_colors(rng, colours.SOIL, len(xy), shift)
    return np.column_stack([xy, np.full(len(xy), z)]), grid_faces(nu, nv), rgba


def _double_sided(position: np.ndarray, front: np.ndarray, back: np.ndarray,
                  index: np.ndarray) -> pyrender.Mesh:
    """A mesh whose triangles (index (F, 3) into position (V, 3)) show colour `front`
    ((V, 3) sRGB in [0, 1]) from the side their winding faces and `back` from the other:
    each is drawn twice, the copy wound the other way, and back-face culling keeps the
    one facing the camera."""
    n = len(position)
    alpha = np.ones((2 * n, 1))
    material = pyrender.MetallicRoughnessMaterial(baseColorFactor=(1.0, 1.0, 1.0, 1.0),
                                                  alphaMode="OPAQUE")
    primitive = pyrender.Primitive(
        positions=np.concatenate([position, position]).astype(np.float32),
        color_0=np.hstack([np.concatenate([front, back]), alpha]).astype(np.float32),
        indices=np.concatenate([index, index[:, ::-1] + n]).astype(np.uint32),
        material=material)
    return pyrender.Mesh([primitive])


def instance_offsets(plants: list[Plant]) -> list[int]:
    """Per plant, what its flowers' ids are offset by in a render of `plants` together: 0
    for the first, then past the ids of the plants before it."""
    return [int(v) for v in np.cumsum([0] + [max((f.id for f in p.flowers), default=-1) + 1
                                             for p in plants[:-1]])]


class PlantRenderer:
    """Renders plants (and a ground) from any camera pose; build once, render many.

    plants: placed in the bed frame (metres). config: lighting and surroundings. camera:
    its clipping distances are used. The instance id of flower `f` of plant `p` is
    `instance_id(p, f)`: the flower's own id for plant 0, then offset past the ids of the
    plants before it.
    """

    def __init__(self, plants: list[Plant] | Plant, config: RenderConfig | None = None,
                 camera: CameraConfig | None = None):
        self.plants = [plants] if isinstance(plants, Plant) else list(plants)
        self.config = cfg = config or RenderConfig()
        self.camera = camera or CameraConfig()
        self._offsets = instance_offsets(self.plants)

        # Everything in one list of triangles; `code` is each face's instance + 1 (0: none).
        vertices, faces, rgba, part, code = [], [], [], [], []
        count = 0
        for plant, offset in zip(self.plants, self._offsets, strict=True):
            vertices.append(np.asarray(plant.mesh.vertices, np.float64))
            faces.append(np.asarray(plant.mesh.faces, np.int64) + count)
            rgba.append(np.asarray(plant.mesh.visual.vertex_colors, np.uint8))
            part.append(np.asarray(plant.face_part, np.int64))
            code.append(np.where(plant.face_flower >= 0, plant.face_flower + offset + 1, 0))
            count += len(vertices[-1])
        plant_faces = sum(len(f) for f in faces)
        if cfg.ground_margin_m is not None:
            bounds = np.array([p.mesh.bounds for p in self.plants])
            bounds = np.stack([bounds[:, 0].min(0), bounds[:, 1].max(0)])
            soil = [np.asarray(p.mesh.vertices)[p.mesh.faces[p.face_part == Part.SOIL], 2]
                    for p in self.plants]
            lowest = min((z.min() for z in soil if z.size), default=0.0)
            ground_z = lowest - 0.001 if cfg.ground_z_m is None else cfg.ground_z_m
            ground = _ground(bounds, cfg.ground_margin_m, ground_z)
            vertices.append(ground[0])
            faces.append(ground[1] + count)
            rgba.append(ground[2])
            part.append(np.full(len(ground[1]), int(Part.SOIL)))
            code.append(np.zeros(len(ground[1]), np.int64))
        vertices, faces = np.concatenate(vertices), np.concatenate(faces)
        part, code = np.concatenate(part), np.concatenate(code)
        albedo = srgb_to_linear(np.concatenate(rgba)[:, :3] / 255.0)
        translucency = np.zeros(len(Part))
        for p, value in TRANSLUCENCY.items():
            translucency[p] = value
        # The flat ground hides no sky or sun (both are above it): only plants cast shadows,
        # so the soil discs' hollows below the ground's level do not turn black.
        lighting = _Lighting(vertices, faces[:plant_faces], cfg)
        face_normal = _triangle_normals(vertices, faces)
        if cfg.smooth:
            normals = np.zeros_like(vertices)
            for k in range(3):
                np.add.at(normals, faces[:, k], face_normal)
            vertex_part = np.zeros(len(vertices), np.int64)
            vertex_part[faces.ravel()] = np.repeat(part, 3)
            front, back = lighting.colors(vertices, _unit(normals), albedo,
                                          translucency[vertex_part])
        else:
            centre = vertices[faces].mean(1)
            front, back = lighting.colors(centre, _unit(face_normal),
                                          albedo[faces].mean(1), translucency[part])

        self._scene = pyrender.Scene(ambient_light=np.zeros(3),
                                     bg_color=np.array([*cfg.background_rgb, 255]) / 255.0)
        self._seg: dict[pyrender.Node, np.ndarray] = {}
        for value in np.unique(code):
            mine = np.flatnonzero(code == value)
            if cfg.smooth:
                used, inverse = np.unique(faces[mine], return_inverse=True)
                mesh = _double_sided(vertices[used], front[used], back[used],
                                     inverse.reshape(-1, 3))
            else:
                mesh = _double_sided(vertices[faces[mine]].reshape(-1, 3),
                                     np.repeat(front[mine], 3, axis=0),
                                     np.repeat(back[mine], 3, axis=0),
                                     np.arange(3 * len(mine)).reshape(-1, 3))
            node = self._scene.add(mesh)
            self._seg[node] = np.array([(value >> 16) & 255, (value >> 8) & 255, value & 255])
        default = self.camera
        self._camera = pyrender.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=default.znear_m,
                                                 zfar=default.zfar_m)
        self._camera_node = self._scene.add(self._camera, pose=np.eye(4))

    def instance_id(self, plant_index: int, flower_id: int) -> int:
        """Value that flower `flower_id` of plant `plant_index` takes in `instance`."""
        return int(self._offsets[plant_index]) + flower_id

    def flower_of(self, instance: int) -> tuple[int, int]:
        """(plant index, flower id) of an instance value (>= 0)."""
        plant_index = int(np.searchsorted(self._offsets, instance, side="right")) - 1
        return plant_index, int(instance - self._offsets[plant_index])

    def render(self, camera_to_bed: np.ndarray, intrinsics: Intrinsics,
               outputs: Output = Output.ALL) -> RenderOutput:
        """What a camera at `camera_to_bed` ((4, 4), OpenCV axes, metres, bed frame) with
        `intrinsics` (pixels) sees: the images in `outputs`."""
        if self._scene is None:
            raise RuntimeError("PlantRenderer used after close()")
        cam = self._camera
        cam.fx, cam.fy = intrinsics.fx, intrinsics.fy
        # pyrender's principal point is measured from the image's top-left corner, the
        # same pixel convention as ours (flowerpose.sim.camera).
        cam.cx, cam.cy = intrinsics.cx, intrinsics.cy
        self._scene.set_pose(self._camera_node, opencv_to_opengl(camera_to_bed))
        renderer = _offscreen(intrinsics.width, intrinsics.height)
        flags = pyrender.RenderFlags
        rgb = depth = instance = None
        if outputs & Output.RGB:
            rgb = np.ascontiguousarray(renderer.render(self._scene, flags=flags.FLAT)[0])
        if outputs & (Output.DEPTH | Output.INSTANCE):
            # pyrender's segmentation pass samples pixel centres (no multisampling): depth
            # exact there and consistent with the masks. Every node is in the map
            # (non-flowers as 0) so that leaves hide flowers.
            seg, z = renderer.render(self._scene, flags=flags.SEG, seg_node_map=self._seg)
            if outputs & Output.DEPTH:
                depth = np.array(z, np.float32)
            if outputs & Output.INSTANCE:
                code = seg.astype(np.int32)
                instance = (code[..., 0] << 16 | code[..., 1] << 8 | code[..., 2]) - 1
        return RenderOutput(rgb, depth, instance)

    def close(self) -> None:
        """Let go of the scene (safe to call twice, and while MuJoCo renders). The shared
        OffscreenRenderer stays for the process; the scene's GL buffers are freed when
        another scene renders."""
        self._scene = None
        self._seg = {}

    def __enter__(self) -> PlantRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
