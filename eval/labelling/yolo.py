"""YOLO labels (Ultralytics' detection and segmentation format) and its `data.yaml`.

Each image `images/<split>/NAME.png` has `labels/<split>/NAME.txt`: one line per instance,
`class x1 y1 x2 y2 ...`, the instance's outline as a polygon of pixel centres normalised by
the image's width and height (0-1). Ultralytics trains segmentation on these lines and
detection on the polygons' boxes; an image without flowers has an empty file. A mask in
several pieces (a flower cut by a leaf) is one polygon: the pieces' outlines joined by
zero-width bridges, as Ultralytics' own COCO converter joins them, so its box is the whole
instance's. Holes in a mask are not kept (the format has none).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.distance import cdist

from flowerpose.atomic import write_text


def outline(mask: np.ndarray) -> np.ndarray:
    """(K, 2) int (column, row) indices of the boundary pixels, in order, of one polygon
    around a mask ((H, W) bool, not empty): its outer contours, each further piece joined
    to the largest by a bridge out from the largest's nearest point and back; at least 3
    points."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL,
                                   cv2.CHAIN_APPROX_SIMPLE)
    parts = sorted((c.reshape(-1, 2) for c in contours), key=len, reverse=True)
    first, rest = parts[0], parts[1:]
    if rest:
        pairs = [np.unravel_index(np.argmin(cdist(first, part)), (len(first), len(part)))
                 for part in rest]
        attach = np.array([i for i, _ in pairs])
        order = np.argsort(attach, kind="stable")
        pieces = np.split(first, attach[order] + 1)
        joined = [pieces[0]]
        for k, piece in zip(order, pieces[1:], strict=True):
            part = np.roll(rest[k], -pairs[k][1], axis=0)
            joined += [part, part[:1], first[attach[k]][None], piece]
        first = np.concatenate(joined)
    if len(first) < 3:
        first = np.resize(first, (3, 2))
    return first


def label_line(class_index: int, mask: np.ndarray) -> str:
    """One label line of an instance's full-image mask ((H, W) bool, not empty)."""
    height, width = mask.shape
    corners = (outline(mask) + 0.5) / [width, height]
    return f"{class_index} " + " ".join(f"{v:.6f}" for v in corners.ravel())


def write_labels(path: Path, lines: list[str]) -> Path:
    """One image's label file (empty: an image without instances)."""
    return write_text(path, "".join(f"{line}\n" for line in lines))


def write_data_yaml(path: Path, splits: dict[str, str], names: list[str]) -> Path:
    """Ultralytics' dataset file: the root (this folder, absolute), each split's image
    folder relative to it, and the class names by index."""
    root = path.parent.resolve()
    lines = ["# A flowerpose dataset (dataset.json says how it was made). Moved elsewhere, give",
             "# its new folder as path (Ultralytics takes a relative path under its datasets",
             "# folder, and this file's own folder when path is left out).",
             f"path: {_quoted(str(root))}"]
    lines += [f"{split}: {_quoted(folder)}" for split, folder in splits.items()]
    lines += [f"nc: {len(names)}", "names:"] + [f"  {k}: {_quoted(n)}" for k, n in
                                                 enumerate(names)]
    return write_text(path, "\n".join(lines) + "\n")


def _quoted(text: str) -> str:
    """A YAML double-quoted scalar (JSON's string escapes are YAML's)."""
    return json.dumps(text)
