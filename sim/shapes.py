"""Mesh primitives in their own local frames: blades, surfaces of revolution, tubes, frames.

All lengths in metres. Functions return `(vertices (V, 3) float64, faces (F, 3) int64)`.
"""

from __future__ import annotations

import numpy as np


def grid_faces(nu: int, nv: int) -> np.ndarray:
    """Two triangles per cell of an nu x nv vertex grid indexed u * nv + v."""
    u, v = np.meshgrid(np.arange(nu - 1), np.arange(nv - 1), indexing="ij")
    a = (u * nv + v).ravel()
    b, c, d = a + 1, a + nv, a + nv + 1
    return np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])


def blade(x: np.ndarray, half_width: np.ndarray, nv: int) -> tuple[np.ndarray, np.ndarray,
                                                                   np.ndarray]:
    """A flat blade along +x in the z = 0 plane, symmetric about the x axis.

    x: (nu,) positions along the blade; half_width: (nu,) half widths there.
    Returns vertices (nu * nv, 3), faces, and s (nu * nv,) in [-1, 1]: the lateral
    position as a fraction of the half width (callers shape z from it).
    """
    s = np.linspace(-1.0, 1.0, nv)
    xx = np.repeat(x, nv)
    ss = np.tile(s, len(x))
    vertices = np.stack([xx, ss * np.repeat(half_width, nv), np.zeros_like(xx)], 1)
    return vertices, grid_faces(len(x), nv), ss


def lathe(radius: np.ndarray, height: np.ndarray, sectors: int) -> tuple[np.ndarray, np.ndarray]:
    """A surface of revolution about +z from a profile (radius[k], height[k]).

    A profile end with radius 0 becomes a single pole vertex, so closed bodies (buds,
    fruit, anthers) and open ones (a calyx cone) come from the same call.
    """
    radius = np.asarray(radius, np.float64)
    height = np.asarray(height, np.float64)
    pole_start, pole_end = radius[0] == 0.0, radius[-1] == 0.0
    rings = np.arange(int(pole_start), len(radius) - int(pole_end))
    angle = np.linspace(0.0, 2.0 * np.pi, sectors, endpoint=False)
    ring_xyz = np.stack([
        (radius[rings, None] * np.cos(angle)).ravel(),
        (radius[rings, None] * np.sin(angle)).ravel(),
        np.repeat(height[rings], sectors),
    ], 1)
    nr = len(rings)
    k, j = np.meshgrid(np.arange(nr - 1), np.arange(sectors), indexing="ij")
    a = (k * sectors + j).ravel()
    b = (k * sectors + (j + 1) % sectors).ravel()
    faces = [np.stack([a, b, a + sectors], 1), np.stack([b, b + sectors, a + sectors], 1)]
    vertices = [ring_xyz]
    j = np.arange(sectors)
    if pole_start:
        vertices.append([[0.0, 0.0, height[0]]])
        faces.append(np.stack([np.full(sectors, len(ring_xyz)), (j + 1) % sectors, j], 1))
    if pole_end:
        pole = len(ring_xyz) + int(pole_start)
        last = (nr - 1) * sectors
        vertices.append([[0.0, 0.0, height[-1]]])
        faces.append(np.stack([last + j, last + (j + 1) % sectors, np.full(sectors, pole)], 1))
    return np.concatenate(vertices).astype(np.float64), np.concatenate(faces).astype(np.int64)


def cubic_bezier(p0, p1, p2, p3, n: int) -> np.ndarray:
    """(n, 3) points of the cubic Bezier curve with control points p0..p3 (metres)."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    return ((1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t ** 2 * p2
            + t ** 3 * p3)


def tube(path: np.ndarray, radius: float, sides: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """An open tube of `radius` along `path` ((n, 3) points, metres).

    Cross-sections follow rotation-minimising frames (double reflection), so the tube does
    not twist or collapse where the path turns through vertical.
    """
    path = np.asarray(path, np.float64)
    tangent = np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    helper = np.eye(3)[np.argmin(np.abs(tangent[0]))]
    ref = np.cross(tangent[0], helper)
    normals = [ref / np.linalg.norm(ref)]
    # The frame propagates from one path sample to the next: a short loop over the
    # curve's control samples (tens), never over points of a cloud.
    for i in range(len(path) - 1):
        v1 = path[i + 1] - path[i]
        c1 = v1 @ v1
        r_l = normals[i] - (2.0 / c1) * (v1 @ normals[i]) * v1
        t_l = tangent[i] - (2.0 / c1) * (v1 @ tangent[i]) * v1
        v2 = tangent[i + 1] - t_l
        c2 = v2 @ v2
        normals.append(r_l - (2.0 / c2) * (v2 @ r_l) * v2 if c2 > 1e-12 else r_l)
    normal = np.asarray(normals)
    binormal = np.cross(tangent, normal)
    angle = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)
    ring = (np.cos(angle)[None, :, None] * normal[:, None]
            + np.sin(angle)[None, :, None] * binormal[:, None])
    vertices = (path[:, None] + radius * ring).reshape(-1, 3)
    k, j = np.meshgrid(np.arange(len(path) - 1), np.arange(sides), indexing="ij")
    a = (k * sides + j).ravel()
    b = (k * sides + (j + 1) % sides).ravel()
    faces = np.concatenate([np.stack([a, b, a + sides], 1), np.stack([b, b + sides, a + sides], 1)])
    return vertices, faces


def frame(z_axis: np.ndarray, twist: float) -> np.ndarray:
    """(3, 3) rotation whose columns are local x, y, z in the parent frame.

    z_axis: (3,) unit vector that local +z maps to; twist: rotation about it, radians.
    """
    z = np.asarray(z_axis, np.float64) / np.linalg.norm(z_axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(twist), np.sin(twist)
    return np.stack([c * x + s * y, -s * x + c * y, z], 1)


def spherical(polar: float, azimuth: float) -> np.ndarray:
    """(3,) unit vector at `polar` radians from +z and `azimuth` radians from +x."""
    return np.array([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth),
                     np.cos(polar)])
