"""A generated plant as MuJoCo contact geometry: the surfaces a tool can touch or push.

MuJoCo collides a mesh by its convex hull, so a plant's thin, curved surfaces go in as
many small patches: the faces of each piece (a leaflet, a petiole, one flower's petals) cut
by a grid of `cell_m` cubes, each patch given `thickness_m` so its hull has a volume. A
patch 1 cm across follows a petal's cupping or a stem's bend to under a millimetre.

Leaflets and petioles are compliant: each piece is a body on a ball joint at its base (a
leaflet where it meets its petiole, a petiole at the crown), held by a spring, so a tool
pushes it aside and the displacement is simulated. Flowers, peduncles, sepals, buds, fruit
and the crown stand still: touching another flower is a failure whatever it does next.
The soil is left out (the planner keeps the tool above it). Metres, bed frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from flowerpose.errors import InputError
from flowerpose.sim.pieces import Part

if TYPE_CHECKING:  # the plant's mesh needs trimesh, which the core install lacks
    from flowerpose.sim.plant import Plant

#: Pieces that bend out of a tool's way, and the part each is attached to.
COMPLIANT = {Part.LEAF: Part.PETIOLE, Part.PETIOLE: Part.CROWN}


@dataclass(frozen=True)
class ContactConfig:
    """How the plant is cut into contact patches and how its leaves give way."""

    cell_m: float = 0.01
    """Edge of the grid cubes that cut each piece into convex patches, metres."""
    thickness_m: float = 0.001
    """Thickness given to each patch (a leaf or petal is about 0.3-0.5 mm), metres."""
    stiffness_nm_per_rad: float = 0.02
    """Spring of a leaflet's or petiole's ball joint, N·m per radian: about 12 gram-force
    at the tip of a 4 cm leaflet holds it 1 cm aside."""
    damping_nms_per_rad: float = 2e-4
    """Damping of those joints, N·m·s per radian (near critical for a 1-2 g leaflet)."""
    density_kg_m3: float = 700.0
    """Density of leaf tissue, for the patches' mass."""
    timestep_s: float = 0.002
    """Physics step while the bot is near the plant, seconds: a tenth of a 1-2 g leaflet's
    period on its spring (about 35 ms)."""

    def __post_init__(self):
        for name in ("cell_m", "thickness_m", "stiffness_nm_per_rad", "damping_nms_per_rad",
                     "density_kg_m3", "timestep_s"):
            if not getattr(self, name) > 0:
                raise InputError(name, f"must be positive, got {getattr(self, name)}")


@dataclass(frozen=True)
class PlantPatches:
    """The plant's contact patches.

    hulls: one (K, 3) array of points a patch is the convex hull of, bed frame.
    part: (P,) `Part` of each patch. flower: (P,) open-flower id, else -1.
    piece: (P,) the connected piece each patch was cut from.
    bases: the compliant pieces' joint positions, piece id -> (3,) bed frame.
    """

    hulls: list[np.ndarray]
    part: np.ndarray
    flower: np.ndarray
    piece: np.ndarray
    bases: dict[int, np.ndarray]


def plant_patches(plant: Plant, config: ContactConfig = ContactConfig()) -> PlantPatches:
    """Cut the plant's surfaces (soil left out) into convex patches."""
    import trimesh

    mesh = plant.mesh
    pieces = trimesh.graph.connected_component_labels(mesh.face_adjacency,
                                                      node_count=len(mesh.faces))
    keep = np.flatnonzero(plant.face_part != int(Part.SOIL))
    cells = np.floor(mesh.triangles_center[keep] / config.cell_m).astype(np.int64)
    keys = np.column_stack([pieces[keep], plant.face_part[keep], cells])
    _, first, owner = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    owner = owner.ravel()
    order = np.argsort(owner, kind="stable")
    bounds = np.searchsorted(owner[order], np.arange(len(first) + 1))
    half = config.thickness_m / 2
    hulls = []
    for k in range(len(first)):
        points = mesh.vertices[np.unique(mesh.faces[keep[order[bounds[k]:bounds[k + 1]]]])]
        # Thicken across the patch's flattest direction(s): its hull then has a volume.
        _, spread, axes = np.linalg.svd(points - points.mean(0), full_matrices=False)
        spread = np.r_[spread, np.zeros(3 - len(spread))]
        axes = np.vstack([axes, np.eye(3)])[:3]
        offsets = [half * axes[2], -half * axes[2]]
        if spread[1] < half:  # a sliver: thicken it both ways
            offsets += [half * axes[1], -half * axes[1]]
        hulls.append(np.vstack([points + o for o in offsets]))
    faces = keep[first]
    part, flower, piece = plant.face_part[faces], plant.face_flower[faces], pieces[faces]
    return PlantPatches(hulls, part, flower, piece, _bases(mesh, pieces, plant.face_part))


def _bases(mesh, pieces: np.ndarray, face_part: np.ndarray) -> dict[int, np.ndarray]:
    """Each compliant piece's joint: its vertex nearest the part it grows from."""
    from scipy.spatial import cKDTree

    bases = {}
    for part, parent in COMPLIANT.items():
        parent_vertices = np.unique(mesh.faces[face_part == int(parent)])
        if not len(parent_vertices):
            continue
        tree = cKDTree(mesh.vertices[parent_vertices])
        for piece in np.unique(pieces[face_part == int(part)]):
            vertices = mesh.vertices[np.unique(mesh.faces[pieces == piece])]
            nearest = tree.query(vertices)[0]
            bases[int(piece)] = vertices[int(np.argmin(nearest))]
    return bases


def add_plant(spec, patches: PlantPatches, config: ContactConfig = ContactConfig()) -> list:
    """Add the patches to a MuJoCo `MjSpec` (`mujoco.MjSpec`): compliant pieces as bodies
    on sprung ball joints, the rest fixed to the world. Plant geoms collide with geoms of
    contype 1 (the tool and head) and not with each other. Returns the geoms' names in
    patch order (`model.geom(name).id` after compiling)."""
    import mujoco

    bodies = {}
    for piece, base in patches.bases.items():
        body = spec.worldbody.add_body(name=f"plant_piece_{piece}", pos=base.tolist())
        body.add_joint(name=f"plant_joint_{piece}", type=mujoco.mjtJoint.mjJNT_BALL,
                       stiffness=config.stiffness_nm_per_rad,
                       damping=config.damping_nms_per_rad, armature=1e-7)
        bodies[piece] = (body, base)
    names = []
    for k, hull in enumerate(patches.hulls):
        body, origin = bodies.get(int(patches.piece[k]), (spec.worldbody, np.zeros(3)))
        centre = hull.mean(0)
        spec.add_mesh(name=f"plant_mesh_{k}", uservert=(hull - centre).ravel().tolist())
        name = f"plant_patch_{k}"
        body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"plant_mesh_{k}",
                      pos=(centre - origin).tolist(), contype=0, conaffinity=1, group=4,
                      density=config.density_kg_m3)
        names.append(name)
    return names
