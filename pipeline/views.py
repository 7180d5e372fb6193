"""Pictures of the projected views with their detections drawn, like the paper's Fig. 5."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from flowerpose.atomic import write_image
from flowerpose.pipeline.detection import Detection
from flowerpose.pipeline.grid import Projection

BOX_COLOUR = (255, 0, 200)  # magenta RGB: stands out on white, green and brown


#: The scale bar's length, metres.
SCALE_BAR_M = 0.05


def draw_detections(projection: Projection, detections: list[Detection],
                    flower_ids: list[int | None] | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB: the view with each detection's outline and box, numbered with
    the id of the flower it became in flowers.json (`flower_ids`; none for a detection
    that became no flower), and a 5 cm scale bar."""
    image = projection.image.copy()
    for k, det in enumerate(detections):
        x0, y0, x1, y1 = det.box
        contours, _ = cv2.findContours(det.mask.astype(np.uint8), cv2.RETR_EXTERNAL,
                                       cv2.CHAIN_APPROX_SIMPLE, offset=(x0, y0))
        cv2.drawContours(image, contours, -1, (255, 230, 0), 1)
        cv2.rectangle(image, (x0, y0), (x1 - 1, y1 - 1), BOX_COLOUR, 1)
        flower = flower_ids[k] if flower_ids is not None and k < len(flower_ids) else None
        if flower is not None:
            _text(image, str(flower), (x0, max(y0 - 3, 10)), BOX_COLOUR)
    _scale_bar(image, projection.pixel_size_m)
    return image


def _text(image: np.ndarray, text: str, at: tuple[int, int], colour) -> None:
    """Text with a dark outline, readable on white petals and dark leaves alike."""
    for thickness, ink in ((3, (0, 0, 0)), (1, colour)):
        cv2.putText(image, text, at, cv2.FONT_HERSHEY_SIMPLEX, 0.4, ink, thickness,
                    cv2.LINE_AA)


def _scale_bar(image: np.ndarray, pixel_size_m: float) -> None:
    length = int(round(SCALE_BAR_M / pixel_size_m))
    height = image.shape[0]
    if length < 4 or length > image.shape[1] - 10:
        return
    y = height - 8
    cv2.line(image, (6, y), (6 + length, y), (0, 0, 0), 3)
    cv2.line(image, (6, y), (6 + length, y), (255, 255, 255), 1)
    _text(image, f"{SCALE_BAR_M * 100:g} cm", (8 + length, y + 4), (255, 255, 255))


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
                detections: list[list[Detection]],
                flower_ids: list[list[int | None]] | None = None) -> list[Path]:
    """Each view as `view_<name>.png` and all of them as `views.png` in out_dir; boxes
    numbered with their flower's id (`FlowerResult.detection_flowers`)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    ids = flower_ids or [None] * len(projections)
    drawn = {p.view.name: draw_detections(p, d, i)
             for p, d, i in zip(projections, detections, ids, strict=True)}
    paths = []
    for name, image in drawn.items():
        path = out_dir / f"view_{name}.png"
        write_image(path, image)
        paths.append(path)
    path = out_dir / "views.png"
    write_image(path, montage(drawn))
    return paths + [path]
