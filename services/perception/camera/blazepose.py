"""BlazePose (MediaPipe Pose, "full" landmark model) in numpy + OpenCV on Google's LiteRT runtime.

Image coordinates are pixels of the input frame, x right, y down.

**Detector** (``pose_detection.tflite``): the RGB frame letterboxed into 224 × 224 (aspect kept,
black border), values in [−1, 1]. 2254 SSD anchors of fixed size, centres on the grids of strides
8, 16 and 32 (28² · 2 + 14² · 2 + 7² · 6). Per anchor 12 regressors in input pixels: box centre
offset and size, then 4 keypoint offsets (0: mid-hip, 1: a point whose distance and direction from
0 encode the full body's size and rotation, 2–3: the same for the upper body); score =
sigmoid(clip(logit, ±100)). One person is tracked: the best detection above the threshold,
averaged with the detections overlapping it (IoU > 0.3) weighted by score (MediaPipe's weighted
non-maximum suppression).

**Region of interest** from a centre point c and a size/rotation point p: a square of side
2 |p − c| · 1.25 centred on c, rotated by r = π/2 − atan2(−(p_y − c_y), p_x − c_x) so the body axis
points up in the crop. A crop point (u, v) (pixels of the image, relative to the crop's centre) is
at c + R(r) (u, v) in the image, R(r) = [[cos r, −sin r], [sin r, cos r]].

**Landmarks** (``pose_landmark_full.tflite``): the ROI warped to 256 × 256 (border replicated),
values in [0, 1]. Outputs 39 landmarks × (x, y, z, visibility, presence) in crop pixels
(visibility and presence as logits → sigmoid), the pose presence in [0, 1], a 64 × 64 × 39 heatmap
and 39 × 3 world landmarks in metres, origin between the hips, along the crop's axes (x right,
y down, z away from the camera), turned by R(r) into the image's axes here. As in MediaPipe, each
landmark's (x, y) is refined to the sigmoid(heatmap)-weighted mean cell of the 7 × 7 cells around
it when the largest weight there is ≥ 0.5. Landmarks 0–32 are the body (MediaPipe's topology);
33 (centre) and 34 (size/rotation) give the next frame's ROI as detector keypoints 0 and 1 do
(tracking): the detector runs only when the track is lost (pose presence below the threshold).
MediaPipe's temporal smoothing is left out (the perception point filter smooths).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from services.perception.camera.model import ModelError, ModelPaths

N_BODY = 33
N_LANDMARKS = 39
DETECTOR_SIZE = 224
LANDMARK_SIZE = 256
#: (stride, anchors per cell) of the detector's merged SSD layers.
ANCHOR_GRIDS = ((8, 2), (16, 2), (32, 6))
ROI_SCALE = 1.25
NMS_MIN_IOU = 0.3
SCORE_CLIP = 100.0
#: Auxiliary landmarks that place the next frame's ROI (centre, size/rotation point).
TRACK_CENTRE, TRACK_SCALE = 33, 34
HEATMAP_KERNEL = 7
HEATMAP_MIN_CONFIDENCE = 0.5


def sigmoid(x: np.ndarray) -> np.ndarray:
    """1 / (1 + e^−x), written with tanh so large |x| cannot overflow."""
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def ssd_anchors() -> np.ndarray:
    """(2254, 2) anchor centres (x, y) in [0, 1] of the detector input, in the model's output order."""
    centres = []
    for stride, per_cell in ANCHOR_GRIDS:
        n = math.ceil(DETECTOR_SIZE / stride)
        ys, xs = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij")
        centres.append(np.repeat(np.stack([xs.ravel(), ys.ravel()], axis=1), per_cell, axis=0))
    return np.concatenate(centres)


@dataclass(frozen=True)
class Roi:
    """A rotated square region of the image: centre (px), side (px), rotation (rad, see module doc)."""

    cx: float
    cy: float
    size: float
    rotation: float

    @classmethod
    def from_points(cls, centre: np.ndarray, scale_point: np.ndarray) -> Roi:
        """The ROI of a centre and a size/rotation point (image px), as MediaPipe aligns it."""
        dx, dy = float(scale_point[0] - centre[0]), float(scale_point[1] - centre[1])
        rotation = math.pi / 2 - math.atan2(-dy, dx)
        rotation = rotation - 2 * math.pi * math.floor((rotation + math.pi) / (2 * math.pi))  # [−π, π)
        return cls(float(centre[0]), float(centre[1]), 2.0 * math.hypot(dx, dy) * ROI_SCALE, rotation)

    def rotation_matrix(self) -> np.ndarray:
        c, s = math.cos(self.rotation), math.sin(self.rotation)
        return np.array([[c, -s], [s, c]])

    def crop_to_image(self, n: int) -> np.ndarray:
        """2×3 affine A: pixel q of an n × n crop is at A[:, :2] q + A[:, 2] in the image."""
        rotation = self.rotation_matrix()
        linear = rotation * (self.size / n)
        offset = np.array([self.cx, self.cy]) - rotation @ np.array([self.size / 2, self.size / 2])
        return np.hstack([linear, offset[:, None]])


@dataclass(frozen=True)
class Detection:
    """A detected person: score in [0, 1], box (x0, y0, x1, y1) and 4 keypoints (4, 2), image px."""

    score: float
    box: np.ndarray
    keypoints: np.ndarray

    def roi(self) -> Roi:
        return Roi.from_points(self.keypoints[0], self.keypoints[1])


@dataclass(frozen=True)
class PoseLandmarks:
    """One person's 33 body landmarks.

    ``image`` (33, 2) px; ``visibility``, ``presence`` (33,) in [0, 1]; ``world`` (33, 3) metres,
    origin between the hips, axes of the image (x right, y down, z away from the camera);
    ``score``: pose presence in [0, 1]; ``roi``: where they were found; ``next_roi``: where to look
    in the next frame.
    """

    image: np.ndarray
    visibility: np.ndarray
    presence: np.ndarray
    world: np.ndarray
    score: float
    roi: Roi
    next_roi: Roi

    @property
    def confidence(self) -> np.ndarray:
        """(33,) visibility · presence."""
        return self.visibility * self.presence


def _interpreter(path: Path, threads: int) -> Any:
    try:
        from ai_edge_litert.interpreter import Interpreter
    except ImportError:
        raise ModelError(
            "the camera source needs Google's LiteRT runtime: pip install 'safemimic[camera]' (ai-edge-litert)"
        ) from None
    interpreter = Interpreter(model_path=str(path), num_threads=threads)
    interpreter.allocate_tensors()
    return interpreter


class _Model:
    """A LiteRT model with one float input; outputs looked up by name."""

    def __init__(self, path: Path, threads: int, input_size: int) -> None:
        self.interpreter = _interpreter(path, threads)
        (tensor,) = self.interpreter.get_input_details()
        if tuple(tensor["shape"]) != (1, input_size, input_size, 3):
            raise ModelError(f"{path}: unexpected input shape {tuple(tensor['shape'])}")
        self._input = tensor["index"]
        self._outputs = {d["name"]: d["index"] for d in self.interpreter.get_output_details()}

    def __call__(self, image: np.ndarray, *names: str) -> list[np.ndarray]:
        self.interpreter.set_tensor(self._input, image[None].astype(np.float32, copy=False))
        self.interpreter.invoke()
        return [self.interpreter.get_tensor(self._outputs[name]) for name in names]


class PoseDetector:
    """Stage 1: the best person detection of an RGB frame, or None (see module doc)."""

    def __init__(self, path: Path, threshold: float, threads: int) -> None:
        self.model = _Model(path, threads, DETECTOR_SIZE)
        self.threshold = threshold
        self.anchors = ssd_anchors()

    def __call__(self, rgb: np.ndarray) -> Detection | None:
        height, width = rgb.shape[:2]
        scale = DETECTOR_SIZE / max(width, height)
        offset = np.array([(DETECTOR_SIZE - width * scale) / 2, (DETECTOR_SIZE - height * scale) / 2])
        letterbox = np.array([[scale, 0.0, offset[0]], [0.0, scale, offset[1]]])
        tensor = cv2.warpAffine(rgb, letterbox, (DETECTOR_SIZE, DETECTOR_SIZE), flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0))
        raw, logits = self.model(tensor.astype(np.float32) / 127.5 - 1.0, "Identity", "Identity_1")
        scores = sigmoid(np.clip(logits[0, :, 0], -SCORE_CLIP, SCORE_CLIP))
        keep = np.flatnonzero(scores >= self.threshold)
        if keep.size == 0:
            return None
        regress = raw[0, keep].reshape(len(keep), 6, 2)  # box centre, box size, 4 keypoints
        points = regress + self.anchors[keep, None, :] * DETECTOR_SIZE
        points[:, 1] = regress[:, 1]  # the size is not anchored
        centre, size = points[:, 0], points[:, 1]
        boxes = np.hstack([centre - size / 2, centre + size / 2])
        best = int(np.argmax(scores[keep]))
        members = _iou(boxes[best], boxes) > NMS_MIN_IOU
        weights = scores[keep][members][:, None]
        box = (boxes[members] * weights).sum(axis=0) / weights.sum()
        keypoints = (points[members, 2:] * weights[:, :, None]).sum(axis=0) / weights.sum()
        return Detection(  # letterbox removed: input px → image px
            score=float(scores[keep][best]),
            box=(box.reshape(2, 2) - offset).ravel() / scale,
            keypoints=(keypoints - offset) / scale,
        )


def _iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Intersection over union of ``box`` (4,) with each of ``boxes`` (N, 4), (x0, y0, x1, y1)."""
    low = np.maximum(box[:2], boxes[:, :2])
    high = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(high - low, 0.0, None), axis=1)
    union = _area(box) + _area(boxes) - inter
    return np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)


def refine_from_heatmap(xy: np.ndarray, heatmap: np.ndarray) -> np.ndarray:
    """Landmarks ``xy`` (N, 2) in [0, 1] of the crop, refined by ``heatmap`` (H, W, N) logits (see module doc)."""
    height, width = heatmap.shape[:2]
    refined = xy.copy()
    half = (HEATMAP_KERNEL - 1) // 2
    for i, (x, y) in enumerate(xy):
        col, row = int(x * width), int(y * height)  # truncation, as MediaPipe
        if not (0 <= col < width and 0 <= row < height):
            continue
        rows = slice(max(0, row - half), min(height, row + half + 1))
        cols = slice(max(0, col - half), min(width, col + half + 1))
        weight = sigmoid(heatmap[rows, cols, i].astype(np.float64))
        total = weight.sum()
        if weight.max() >= HEATMAP_MIN_CONFIDENCE and total > 0:
            grid_rows, grid_cols = np.mgrid[rows, cols]
            refined[i] = ((grid_cols * weight).sum() / width / total, (grid_rows * weight).sum() / height / total)
    return refined


def _area(boxes: np.ndarray) -> np.ndarray:
    return np.prod(np.clip(boxes[..., 2:] - boxes[..., :2], 0.0, None), axis=-1)


class PoseLandmarker:
    """Stage 2: the landmarks of the person inside a ROI of an RGB frame (see module doc)."""

    def __init__(self, path: Path, threads: int) -> None:
        self.model = _Model(path, threads, LANDMARK_SIZE)

    def __call__(self, rgb: np.ndarray, roi: Roi) -> PoseLandmarks:
        crop_to_image = roi.crop_to_image(LANDMARK_SIZE)
        crop = cv2.warpAffine(rgb, crop_to_image, (LANDMARK_SIZE, LANDMARK_SIZE),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
        raw, flag, heatmap, world = self.model(crop.astype(np.float32) / 255.0, "Identity", "Identity_1", "Identity_3", "Identity_4")
        raw = raw.reshape(N_LANDMARKS, 5)
        crop_xy = refine_from_heatmap(raw[:, :2].astype(np.float64) / LANDMARK_SIZE, heatmap[0]) * LANDMARK_SIZE
        image = crop_xy @ crop_to_image[:, :2].T + crop_to_image[:, 2]
        world = world.reshape(N_LANDMARKS, 3)[:N_BODY].astype(np.float64)
        world[:, :2] = world[:, :2] @ roi.rotation_matrix().T
        return PoseLandmarks(
            image=image[:N_BODY],
            visibility=sigmoid(raw[:N_BODY, 3].astype(np.float64)),
            presence=sigmoid(raw[:N_BODY, 4].astype(np.float64)),
            world=world,
            score=float(flag.reshape(-1)[0]),
            roi=roi,
            next_roi=Roi.from_points(image[TRACK_CENTRE], image[TRACK_SCALE]),
        )


class BlazePose:
    """Detector + landmarker with tracking: ``pose = blazepose(rgb)`` per frame, None if nobody is seen.

    While the pose presence stays ≥ ``presence_threshold`` the next frame's ROI comes from this
    frame's landmarks; otherwise the detector looks for a person again (in the same frame).
    """

    def __init__(self, paths: ModelPaths, detection_threshold: float = 0.5, presence_threshold: float = 0.5,
                 threads: int = 2) -> None:
        self.detector = PoseDetector(paths.detector, detection_threshold, threads)
        self.landmarker = PoseLandmarker(paths.landmarker, threads)
        self.presence_threshold = presence_threshold
        self._roi: Roi | None = None
        self.detections = 0

    def reset(self) -> None:
        """Forget the track: the next frame starts with the detector."""
        self._roi = None

    def __call__(self, rgb: np.ndarray) -> PoseLandmarks | None:
        if self._roi is not None:
            pose = self.landmarker(rgb, self._roi)
            if pose.score >= self.presence_threshold:
                self._roi = pose.next_roi
                return pose
            self._roi = None
        detection = self.detector(rgb)
        self.detections += 1
        if detection is None:
            return None
        pose = self.landmarker(rgb, detection.roi())
        if pose.score < self.presence_threshold:
            return None
        self._roi = pose.next_roi
        return pose
