"""Labelled mesh pieces: the parts a plant is assembled from, with a label per face."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np


class Part(IntEnum):
    """What a face (or an oracle point) belongs to."""

    SOIL = 0
    LEAF = 1
    PETIOLE = 2
    PEDUNCLE = 3
    PETAL = 4
    RECEPTACLE = 5
    STAMEN = 6
    SEPAL = 7
    BUD = 8
    FRUIT = 9
    CROWN = 10


#: Parts that carry the id of their open flower in `face_flower`.
FLOWER_PARTS = (Part.PETAL, Part.RECEPTACLE, Part.STAMEN, Part.SEPAL)


@dataclass(frozen=True)
class Piece:
    """A triangle mesh with per-vertex colours and per-face labels.

    vertices: (V, 3) float64, metres, in the frame the piece was built in.
    faces: (F, 3) int64 vertex indices. colors: (V, 4) uint8 RGBA.
    part: (F,) int8 `Part` values. flower: (F,) int32 open-flower id or -1.
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    part: np.ndarray
    flower: np.ndarray

    @staticmethod
    def of(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray, part: Part) -> Piece:
        """A piece whose faces all belong to one part and no flower."""
        n = len(faces)
        return Piece(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), colors,
                     np.full(n, int(part), np.int8), np.full(n, -1, np.int32))

    def moved(self, rotation: np.ndarray, translation: np.ndarray) -> Piece:
        """The piece with vertices mapped x -> rotation @ x + translation."""
        return Piece(self.vertices @ np.asarray(rotation).T + translation, self.faces,
                     self.colors, self.part, self.flower)

    def with_flower(self, flower_id: int) -> Piece:
        """The piece with its flower-part faces (petal, receptacle, stamen, sepal) given an id."""
        flower = np.where(np.isin(self.part, [int(p) for p in FLOWER_PARTS]),
                          np.int32(flower_id), self.flower).astype(np.int32)
        return Piece(self.vertices, self.faces, self.colors, self.part, flower)

    def area(self) -> float:
        """Total surface area, square metres."""
        tri = self.vertices[self.faces]
        return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]),
                                          axis=1).sum())


def merge(pieces: list[Piece]) -> Piece:
    """One piece holding all of `pieces` (faces re-indexed, order kept)."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in pieces[:-1]])
    return Piece(
        np.concatenate([p.vertices for p in pieces]),
        np.concatenate([p.faces + off for p, off in zip(pieces, offsets, strict=True)]),
        np.concatenate([p.colors for p in pieces]),
        np.concatenate([p.part for p in pieces]),
        np.concatenate([p.flower for p in pieces]),
    )
