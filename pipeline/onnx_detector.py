"""The built-in ONNX detector: a user's exported box or segmentation model on the grid views.

`detect.detector=onnx:MODEL.onnx` (or `--detector onnx:MODEL.onnx`) runs the model on
onnxruntime (the [onnx] extra), once per view. The contract, for whoever exports a model:

- **Input**: one tensor, (1, 3, H, W) float32, RGB, values 0-1 (the view's 8-bit colours
  divided by 255), channels first. A model with a fixed H and W gets its own size; one
  whose size is dynamic gets `detect.onnx.input_px` square (640). Each view is letterboxed
  as Ultralytics does: scaled by one factor to fit (up or down, bilinear), centred, padded
  with grey 114. Any other normalisation (ImageNet means, BGR) belongs in the exported
  graph.
- **Output** (the first one), either of:
  - boxes, (1, N, 6) or (N, 6): rows [x1, y1, x2, y2, score, class] in the input's pixels,
    after non-maximum suppression (an end-to-end YOLOv10 export, or Ultralytics'
    `export(format="onnx", nms=True)`). Rows of class `detect.onnx.flower_class` scoring at
    least `detect.onnx.score_threshold` become detections; a box's mask is every pixel in
    it that holds a point, as the paper back-projected boxes.
  - a per-pixel flower probability, 0-1: (1, C, h, w) (channel `flower_class`) or
    (1, h, w), at the input's size or any other (resized to it). Pixels from
    `detect.onnx.mask_threshold` on that hold a point form the detections, as connected
    components within the area limits (`detect.min_area_m2`, `detect.max_area_m2`), each
    scored by its mean probability.
- The flower class is 0 for a model trained on `flowerpose dataset` (its only class).

Detections come back in the view's own pixels as `Detection`s, exactly as the colour
detector's, and go on to back-projection, clustering and pose the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from flowerpose.config import require
from flowerpose.errors import InputError, missing_extra
from flowerpose.pipeline.detection import Detection, components


@dataclass(frozen=True)
class OnnxConfig:
    """The built-in ONNX detector (`detect.detector=onnx:MODEL.onnx`): how a user's model
    is fed and read (the module's docstring documents the contract)."""

    input_px: int = 640
    """Side of the square input, pixels, for a model whose input size is not fixed (a
    fixed-size model gets its own size); each view is letterboxed to it (Ultralytics'
    default image size)."""
    score_threshold: float = 0.25
    """A box model's rows scoring below this are dropped (Ultralytics' default
    confidence)."""
    mask_threshold: float = 0.5
    """A segmentation model's pixels count as flower from this probability on."""
    flower_class: int = 0
    """The flower's class index: a box row's class, or a segmentation output's channel. 0
    for a model trained on `flowerpose dataset` (YOLO class 0; COCO category 1, class 0 of
    a model trained with contiguous class indices)."""

    def __post_init__(self):
        require(self.input_px >= 32, "detect.onnx.input_px", "must be at least 32 pixels")
        require(0 <= self.score_threshold <= 1, "detect.onnx.score_threshold",
                "must be within 0-1")
        require(0 < self.mask_threshold <= 1, "detect.onnx.mask_threshold",
                "must be above 0, at most 1")
        require(self.flower_class >= 0, "detect.onnx.flower_class", "must be 0 or more")


class DetectSettings(Protocol):
    """What the ONNX detector reads of the `detect` settings (`detect.DetectConfig`): its
    own section and the area limits of a mask's components, square metres."""

    @property
    def onnx(self) -> OnnxConfig: ...

    @property
    def min_area_m2(self) -> float: ...

    @property
    def max_area_m2(self) -> float: ...


#: onnxruntime's backends in the order tried: a GPU where onnxruntime-gpu has one, else the
#: CPU.
PROVIDERS = ("CUDAExecutionProvider", "CPUExecutionProvider")

#: Grey of the letterbox's padding, 8-bit (Ultralytics' LetterBox), so a model trained
#: with Ultralytics sees what it was trained on.
PAD_GREY = 114


def letterbox(image: np.ndarray, size: tuple[int, int]
              ) -> tuple[np.ndarray, float, tuple[int, int]]:
    """The model's input tensor of one view, and how to map back.

    image: (H, W, 3) uint8 RGB; size: the model's (height, width), pixels. Returns the
    (1, 3, height, width) float32 tensor (RGB 0-1), the scale (input pixels per image
    pixel) and the (left, top) padding, input pixels."""
    height, width = image.shape[:2]
    scale = min(size[0] / height, size[1] / width)
    new_w, new_h = int(round(width * scale)), int(round(height * scale))
    resized = (cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_LINEAR)
               if (new_w, new_h) != (width, height) else image)
    left, top = int(round((size[1] - new_w) / 2 - 0.1)), int(round((size[0] - new_h) / 2 - 0.1))
    canvas = np.full((size[0], size[1], 3), PAD_GREY, np.uint8)
    canvas[top:top + new_h, left:left + new_w] = resized
    tensor = canvas.transpose(2, 0, 1)[None].astype(np.float32) * np.float32(1 / 255)
    return np.ascontiguousarray(tensor), scale, (left, top)


class OnnxDetector:
    """A user's ONNX box or segmentation model (the module's contract) as a `Detector`."""

    def __init__(self, model: str | Path, config: DetectSettings):
        """model: the .onnx file; config: `detect` (its `onnx` section and area limits)."""
        self.model, self.config = Path(model), config
        self.name = f"onnx:{model}"
        try:
            import onnxruntime
        except ModuleNotFoundError:
            raise missing_extra("onnxruntime", f"detect.detector {self.name}") from None
        if not self.model.is_file():
            raise InputError(self.model, "no such ONNX model file")
        try:
            available = onnxruntime.get_available_providers()
            self.session = onnxruntime.InferenceSession(str(self.model), providers=[
                p for p in PROVIDERS if p in available])
        except Exception as err:  # noqa: BLE001 - onnxruntime's own errors, in one line
            raise InputError(self.model, "onnxruntime cannot load it as a model "
                             f"({_first_line(err)})") from None
        inputs = self.session.get_inputs()
        shape = inputs[0].shape if len(inputs) == 1 else []
        if len(shape) != 4 or (isinstance(shape[1], int) and shape[1] != 3):
            raise InputError(self.model, "expected one input of shape (1, 3, H, W) (RGB, "
                             f"channels first), got {[(i.name, i.shape) for i in inputs]}")
        self.input = inputs[0].name
        fixed = [d if isinstance(d, int) and d > 0 else None for d in shape[2:]]
        side = config.onnx.input_px
        self.size = (fixed[0] or side, fixed[1] or side)

    def __call__(self, image: np.ndarray, occupied: np.ndarray,
                 pixel_size_m: float) -> list[Detection]:
        tensor, scale, pad = letterbox(image, self.size)
        try:
            output = np.asarray(self.session.run(None, {self.input: tensor})[0], np.float32)
        except Exception as err:  # noqa: BLE001 - the model's own failure, in one line
            raise InputError(self.model, f"failed on a view ({_first_line(err)})") from None
        shape = output.shape
        if output.ndim in (2, 3) and shape[-1] == 6 and (output.ndim == 2 or shape[0] == 1):
            return self._boxes(output.reshape(-1, 6), scale, pad, occupied)
        if output.ndim in (3, 4) and shape[0] == 1:
            channels = output.reshape(-1, *shape[-2:])
            if self.config.onnx.flower_class >= len(channels):
                raise InputError(self.model, f"its output has {len(channels)} channels; "
                                 f"detect.onnx.flower_class is {self.config.onnx.flower_class}")
            return self._mask(channels[self.config.onnx.flower_class], scale, pad, occupied,
                              pixel_size_m)
        raise InputError(self.model, f"output of shape {list(shape)}: expected boxes (1, N, 6) "
                         "[x1, y1, x2, y2, score, class] or a flower probability (1, C, h, w)")

    def _boxes(self, rows: np.ndarray, scale: float, pad: tuple[int, int],
               occupied: np.ndarray) -> list[Detection]:
        """Detections of box rows ((N, 6), input pixels): box masks of occupied pixels."""
        cfg = self.config.onnx
        rows = rows[(rows[:, 4] >= cfg.score_threshold) & (np.rint(rows[:, 5]) == cfg.flower_class)
                    & np.isfinite(rows).all(1)]
        height, width = occupied.shape
        x = np.clip((rows[:, [0, 2]] - pad[0]) / scale, 0, width)
        y = np.clip((rows[:, [1, 3]] - pad[1]) / scale, 0, height)
        boxes = np.column_stack([np.floor(x.min(1)), np.floor(y.min(1)),
                                 np.ceil(x.max(1)), np.ceil(y.max(1))]).astype(int)
        detections = []
        for (x0, y0, x1, y1), score in zip(boxes, rows[:, 4], strict=True):
            mask = occupied[y0:y1, x0:x1]
            if mask.any():
                detections.append(Detection((int(x0), int(y0), int(x1), int(y1)), mask.copy(),
                                            float(score)))
        return detections

    def _mask(self, probability: np.ndarray, scale: float, pad: tuple[int, int],
              occupied: np.ndarray, pixel_size_m: float) -> list[Detection]:
        """Detections of a flower probability map ((h, w), over the model's input)."""
        if probability.size and (probability.min() < 0 or probability.max() > 1):
            raise InputError(self.model, "its per-pixel output is not a probability in 0-1 "
                             "(end the exported graph with a Sigmoid or Softmax)")
        if probability.shape != self.size:
            probability = cv2.resize(probability, self.size[::-1],
                                     interpolation=cv2.INTER_LINEAR)
        height, width = occupied.shape
        inside = probability[pad[1]:pad[1] + int(round(height * scale)),
                             pad[0]:pad[0] + int(round(width * scale))]
        view = cv2.resize(inside, (width, height), interpolation=cv2.INTER_LINEAR)
        flower = occupied & (view >= self.config.onnx.mask_threshold)
        return components(flower, view, pixel_size_m,
                          (self.config.min_area_m2, self.config.max_area_m2))


def _first_line(err: Exception) -> str:
    text = str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0] if text else ''}"
