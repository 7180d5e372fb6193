"""COCO instance annotations (the `instances_*.json` of COCO, Detectron2 and MMDetection).

One file a split: `images` (id, file_name relative to the split's image folder, width,
height), `annotations` (id, image_id, category_id, bbox [x, y, width, height] in pixels
from the image's top-left corner, area in pixels, iscrowd 0, segmentation as uncompressed
RLE {"size": [height, width], "counts": [...]}, column-major runs starting with
background, as pycocotools' `frPyObjects` reads it) and `categories`. RLE keeps every
instance mask exact, pixel for pixel; pycocotools, Detectron2 (`MASK_FORMAT=bitmask` for
mask heads) and MMDetection decode it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from flowerpose import __version__
from flowerpose.atomic import write_text


def rle(mask: np.ndarray) -> dict:
    """The uncompressed COCO RLE of a full-image mask ((H, W) bool): run lengths in
    column-major order, the first one of background (0 when the first pixel is in)."""
    flat = np.asarray(mask, bool).ravel(order="F")
    changes = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    counts = np.diff(np.concatenate([[0], changes, [flat.size]]))
    if flat.size and flat[0]:
        counts = np.concatenate([[0], counts])
    return {"size": [int(mask.shape[0]), int(mask.shape[1])], "counts": counts.tolist()}


def annotation(annotation_id: int, image_id: int, category_id: int, mask: np.ndarray,
               **extra) -> dict:
    """One instance's COCO annotation from its full-image mask ((H, W) bool, not empty):
    its pixel box, pixel area and RLE; `extra` keys are kept beside them."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    x0, y0 = int(cols[0]), int(rows[0])
    return {"id": annotation_id, "image_id": image_id, "category_id": category_id,
            "bbox": [x0, y0, int(cols[-1]) + 1 - x0, int(rows[-1]) + 1 - y0],
            "area": int(mask.sum()), "iscrowd": 0, "segmentation": rle(mask), **extra}


def write_instances(path: Path, images: list[dict], annotations: list[dict],
                    categories: list[dict], description: str) -> Path:
    """Write one split's instances file (compact JSON, as COCO's own; no date, so the same
    dataset gives the same bytes)."""
    document = {"info": {"description": description, "version": __version__},
                "licenses": [], "images": images, "annotations": annotations,
                "categories": categories}
    return write_text(path, json.dumps(document, separators=(",", ":")))
