"""Pictures of the projected views with their detections drawn, like the paper's Fig. 5."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from flowerpose.atomic import write_image
from flowerpose.pipeline.detect import Detection
from flowerpose.pipeline.grid import Projection

BOX_COLOUR = (255, 0, 200)  # magenta RGB: stands out on white, green and brown


def draw_detections(projection: Projection, detections: list[Detection]) -> np.ndarray:
    """(H, W, 3) uint8 RGB: the view with each detection's outline and box."""
    image = projection.image.copy()
    for det in detections:
        x0, y0, x1, y1 = det.box
        contours, _ = cv2.findContours(det.mask.astype(np.uint8), cv2.RETR_EXTERNAL,
                                       cv2.CHAIN_APPROX_SIMPLE, offset=(x0, y0))
        cv2.drawContours(image, contours, -1, (255, 230, 0), 1)
        cv2.rectangle(image, (x0, y0), (x1 - 1, y1 - 1), BOX_COLOUR, 1)
    return image


def _label(image: np.ndarray, text: str) -> np.ndarray:
    out = image.copy()
    cv2.putText(out, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return out


def montage(images: dict[str, np.ndarray], background: int = 255) -> np.ndarray:
    """One picture of all views: the six faces as an unfolded cube, more views as a grid."""
    height = max(i.shape[0] for i in images.values())
    width = max(i.shape[1] for i in images.values())
    cube = {"+z": (0, 1), "-x": (1, 0), "+y": (1, 1), "+x": (1, 2), "-y": (1, 3), "-z": (2, 1)}
    if set(images) == set(cube):
        cells = {name: cube[name] for name in images}
    else:
        cols = int(np.ceil(np.sqrt(len(images))))
        cells = {name: divmod(i, cols) for i, name in enumerate(images)}
    rows = max(r for r, _ in cells.values()) + 1
    cols = max(c for _, c in cells.values()) + 1
    canvas = np.full((rows * height, cols * width, 3), background, np.uint8)
    for name, (r, c) in cells.items():
        img = _label(images[name], name)
        canvas[r * height:r * height + img.shape[0], c * width:c * width + img.shape[1]] = img
    return canvas


def write_views(out_dir: Path, projections: list[Projection],
                detections: list[list[Detection]]) -> list[Path]:
    """Each view as `view_<name>.png` and all of them as `views.png` in out_dir."""
    out_dir.mkdir(parents=True, exist_ok=True)
    drawn = {p.view.name: draw_detections(p, d)
             for p, d in zip(projections, detections, strict=True)}
    paths = []
    for name, image in drawn.items():
        path = out_dir / f"view_{name}.png"
        write_image(path, image)
        paths.append(path)
    path = out_dir / "views.png"
    write_image(path, montage(drawn))
    return paths + [path]
