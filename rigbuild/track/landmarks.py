"""Facial landmarks in one image: the short-range face detector and the 468-point face mesh network (the first
level of Ma et al. 2016's coarse-to-fine tracking, which starts from a facial landmark predictor).

The two networks are mediapipe 0.10.21's ``face_detection_short_range.tflite`` and ``face_landmark.tflite``
(installed by :mod:`rigbuild.assets.face_models`), run with ai-edge-litert; everything around them is here,
on numpy images:

1. **Detection** (:func:`detect_faces`): the image is letterboxed (zero border) to a square and resized to
   128x128 RGB in [-1, 1]. The network regresses 16 values and one logit per SSD anchor (:func:`ssd_anchors`:
   strides 8 / 16 / 16 / 16, two unit anchors per layer and cell, 16x16x2 + 8x8x6 = 896):
   box centre and size and 6 keypoints (right eye, left eye, nose tip, mouth centre, right and left tragion; the
   subject's right, on the image's left for a frontal face) as offsets in 128-px units from the anchor centre
   (:func:`decode_detections`). Detections scoring >= 0.5 (sigmoid of the logit, clipped at +-100) are merged
   by weighted non-max suppression (IoU 0.3, :func:`weighted_nms`).
2. **Crop** (:func:`roi_from_detection`): a square centred on the box, 1.5 times its longer side, rotated so
   that the eye keypoints are level (the roll); warped to 192x192 RGB in [0, 1] (:func:`crop_roi`).
3. **Landmarks** (:func:`landmarks_in_roi`): 468 (x, y, z) in crop pixels, mapped back to image pixels
   (z scaled as x: relative depth, not mm) and the face-presence score. :func:`roi_from_landmarks` re-crops from
   the landmarks themselves (box of the points, roll from the outer eye corners 33 and 263, scale 1.5), as the
   mediapipe graph does from frame to frame; :class:`FaceLandmarker` runs ``refine`` such extra passes.

Pixel convention: the project's (OpenCV) pixel centres at integer coordinates. Images are RGB (H, W, 3) or
grey (H, W), uint8 (or float in [0, 255]).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

DETECTOR_SIZE = 128
LANDMARK_SIZE = 192
N_LANDMARKS = 468
#: face-mesh indices of the outer eye corners (subject's right eye, image left; subject's left, image right)
RIGHT_EYE_OUTER, LEFT_EYE_OUTER = 33, 263
DETECTOR_KEYPOINTS = ("right_eye", "left_eye", "nose_tip", "mouth_centre", "right_tragion", "left_tragion")


# ============================================================================ detector: anchors, decoding, NMS
def ssd_anchors(input_size: int = DETECTOR_SIZE, strides=(8, 16, 16, 16), per_layer: int = 2) -> np.ndarray:
    """(A, 2) anchor centres in [0, 1] (x, y) of the short-range detector (fixed unit anchor size).

    Consecutive layers with the same stride share a feature map; each layer contributes ``per_layer`` anchors
    per cell (aspect ratio 1 and its interpolated scale). Order: layer group, row, column, anchor.
    """
    out = []
    i = 0
    while i < len(strides):
        j = i
        while j < len(strides) and strides[j] == strides[i]:
            j += 1
        n = int(np.ceil(input_size / strides[i]))
        k = per_layer * (j - i)
        yy, xx = np.mgrid[0:n, 0:n]
        c = np.stack([(xx + 0.5) / n, (yy + 0.5) / n], -1).reshape(-1, 1, 2)
        out.append(np.repeat(c, k, axis=1).reshape(-1, 2))
        i = j
    return np.concatenate(out).astype(np.float64)


@dataclass
class FaceDetection:
    """One face found by the detector, in image pixels.

    box : (4,) x0, y0, x1, y1 px; keypoints : (6, 2) px in :data:`DETECTOR_KEYPOINTS` order; score in [0, 1].
    """

    box: np.ndarray
    keypoints: np.ndarray
    score: float


def decode_detections(raw_boxes: np.ndarray, raw_scores: np.ndarray, anchors: np.ndarray,
                      input_size: int = DETECTOR_SIZE, min_score: float = 0.5, clip: float = 100.0
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decode the detector's (A, 16) regressors and (A,) logits against ``anchors`` (A, 2).

    Returns boxes (N, 4) x0, y0, x1, y1, keypoints (N, 6, 2) x, y, both normalized to the 128-px input [0, 1],
    and scores (N,) for the anchors scoring >= ``min_score``.
    """
    raw_boxes = np.asarray(raw_boxes, np.float64).reshape(-1, 16)
    scores = 1.0 / (1.0 + np.exp(-np.clip(np.asarray(raw_scores, np.float64).reshape(-1), -clip, clip)))
    keep = scores >= min_score
    r, a = raw_boxes[keep] / input_size, anchors[keep]
    c = r[:, 0:2] + a
    half = r[:, 2:4] / 2
    boxes = np.concatenate([c - half, c + half], 1)
    kps = r[:, 4:16].reshape(-1, 6, 2) + a[:, None, :]
    return boxes, kps, scores[keep]


def box_iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N,) intersection over union of one box (4,) with boxes (N, 4), all x0, y0, x1, y1."""
    lo = np.maximum(box[:2], boxes[:, :2])
    hi = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    area = lambda b: np.prod(np.clip(b[..., 2:] - b[..., :2], 0, None), axis=-1)  # noqa: E731
    return inter / np.maximum(area(box) + area(boxes) - inter, 1e-12)


def weighted_nms(boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray, iou: float = 0.3
                 ) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Weighted non-max suppression: the best remaining detection absorbs every one overlapping it by more than
    ``iou``; the merged box and keypoints are the score-weighted means, the score the best's. Best first."""
    order = np.argsort(-scores)
    left = order.copy()
    out = []
    while left.size:
        top = left[0]
        ov = box_iou(boxes[top], boxes[left]) > iou
        grp = left[ov]
        w = scores[grp][:, None]
        out.append(((boxes[grp] * w).sum(0) / w.sum(), (keypoints[grp] * w[:, :, None]).sum(0) / w.sum(),
                    float(scores[top])))
        left = left[~ov]
    return out


# ============================================================================ crops
@dataclass
class Roi:
    """A rotated square region of an image: centre (2,) px (continuous: pixel i spans [i, i + 1)), side px,
    angle rad (the crop's x axis is (cos, sin) in image coordinates, y down)."""

    centre: np.ndarray
    size: float
    angle: float

    def crop_to_image(self, out_size: int) -> np.ndarray:
        """(2, 3) affine map: crop continuous coordinates (0..out_size) -> image continuous coordinates."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        k = self.size / out_size
        A = k * np.array([[c, -s], [s, c]])
        return np.concatenate([A, (self.centre - A @ np.full(2, out_size / 2))[:, None]], 1)


def _as_rgb_float(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"landmarks: expected an (H, W, 3) RGB or (H, W) grey image, got {img.shape}")
    return img.astype(np.float32)


def crop_roi(image: np.ndarray, roi: Roi, out_size: int) -> np.ndarray:
    """(out_size, out_size, 3) float32 crop of ``image`` (0..255) over ``roi`` (bilinear, zero border)."""
    M = roi.crop_to_image(out_size)
    # integer-centred indices: src_idx = M @ (dst_idx + 0.5) - 0.5
    Mi = M.copy()
    Mi[:, 2] = M[:, 2] + M[:, :2] @ np.full(2, 0.5) - 0.5
    return cv2.warpAffine(_as_rgb_float(image), Mi, (out_size, out_size),
                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def roll_angle(p_right: np.ndarray, p_left: np.ndarray) -> float:
    """The roll (rad) that levels the line from the subject's right eye (image left) to the left eye."""
    d = np.asarray(p_left, float) - np.asarray(p_right, float)
    return float(np.arctan2(d[1], d[0]))


def roi_from_box(box: np.ndarray, angle: float, scale: float = 1.5) -> Roi:
    """The square crop around ``box`` (x0, y0, x1, y1 continuous px): ``scale`` times its longer side."""
    box = np.asarray(box, float)
    return Roi((box[:2] + box[2:]) / 2, float(scale * max(box[2] - box[0], box[3] - box[1])), angle)


def roi_from_detection(det: FaceDetection, scale: float = 1.5) -> Roi:
    """The landmark crop for a detection (box in project px; the eye keypoints give the roll)."""
    return roi_from_box(det.box + 0.5, roll_angle(det.keypoints[0], det.keypoints[1]), scale)


def roi_from_landmarks(points: np.ndarray, scale: float = 1.5) -> Roi:
    """The landmark crop from a previous pass's (468, 2+) points (project px): their box, roll from 33 / 263."""
    p = np.asarray(points, float)[:, :2] + 0.5
    box = np.concatenate([p.min(0), p.max(0)])
    return roi_from_box(box, roll_angle(p[RIGHT_EYE_OUTER], p[LEFT_EYE_OUTER]), scale)


# ============================================================================ the networks
def _interpreter(name: str, num_threads: int):
    from ai_edge_litert.interpreter import Interpreter

    from rigbuild.assets.face_models import model_path

    it = Interpreter(model_path=str(model_path(name)), num_threads=num_threads)
    it.allocate_tensors()
    return it


def _run(it, x: np.ndarray) -> dict[str, np.ndarray]:
    it.set_tensor(it.get_input_details()[0]["index"], x[None].astype(np.float32))
    it.invoke()
    return {d["name"]: it.get_tensor(d["index"]).copy() for d in it.get_output_details()}


@dataclass
class FaceLandmarks:
    """The 468 face-mesh landmarks of one face in one image.

    points : (468, 3) x, y project px and z (relative depth in the same px scale; smaller is nearer);
    presence : face-presence score in [0, 1]; roi : the last crop used; detection : the detector's face.
    """

    points: np.ndarray
    presence: float
    roi: Roi
    detection: FaceDetection | None = None


class FaceLandmarker:
    """Both networks, loaded once (``num_threads`` CPU threads each).

    ``refine``: extra passes re-cropped from the landmarks (:func:`roi_from_landmarks`) after the first
    (detector) crop; ``min_presence``: faces whose presence score is lower are dropped.
    """

    def __init__(self, num_threads: int = 1, refine: int = 1, min_presence: float = 0.5,
                 min_detection_score: float = 0.5):
        self.detector = _interpreter("face_detection_short_range.tflite", num_threads)
        self.mesh = _interpreter("face_landmark.tflite", num_threads)
        self.anchors = ssd_anchors()
        self.refine, self.min_presence, self.min_score = int(refine), float(min_presence), float(min_detection_score)

    def _detect_window(self, image: np.ndarray, roi: Roi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Raw detections in the axis-aligned square ``roi`` of ``image``: boxes (N, 4), keypoints (N, 6, 2)
        in project px, scores (N,)."""
        x = crop_roi(image, roi, DETECTOR_SIZE) / 127.5 - 1.0
        out = _run(self.detector, x)
        boxes, kps, scores = decode_detections(out["regressors"][0], out["classificators"][0], self.anchors,
                                               min_score=self.min_score)
        to_px = lambda n: roi.centre + roi.size * (n - 0.5) - 0.5  # noqa: E731
        return np.concatenate([to_px(boxes[:, :2]), to_px(boxes[:, 2:])], 1), to_px(kps), scores

    def detect_faces(self, image: np.ndarray, min_window_px: float = 192.0) -> list[FaceDetection]:
        """Faces in ``image``, best first (boxes and keypoints in project px).

        The whole image (letterboxed: the centred square, zero border) first; when it holds no face (the
        short-range network wants a face of about a fifth of its input or more), overlapping square windows of
        half the size, and so on down to ``min_window_px``, all merged by :func:`weighted_nms`.
        """
        H, W = np.shape(image)[:2]
        L = float(max(H, W))
        boxes, kps, scores = self._detect_window(image, Roi(np.array([W / 2, H / 2]), L, 0.0))
        side = L / 2
        while not scores.size and side >= min_window_px:
            found = []
            for cy in np.arange(side / 2, max(H - side / 2, side / 2) + 1e-6, side / 2):
                for cx in np.arange(side / 2, max(W - side / 2, side / 2) + 1e-6, side / 2):
                    found.append(self._detect_window(image, Roi(np.array([cx, cy]), side, 0.0)))
            boxes, kps, scores = (np.concatenate([f[i] for f in found]) for i in range(3))
            side /= 2
        return [FaceDetection(b, k, s) for b, k, s in weighted_nms(boxes, kps, scores)]

    def landmarks_in_roi(self, image: np.ndarray, roi: Roi) -> tuple[np.ndarray, float]:
        """(468, 3) project px landmarks and the presence score for the crop ``roi`` of ``image``."""
        x = crop_roi(image, roi, LANDMARK_SIZE) / 255.0
        out = _run(self.mesh, x)
        raw = [v for v in out.values() if v.size == 3 * N_LANDMARKS][0].reshape(N_LANDMARKS, 3).astype(np.float64)
        logit = float([v for v in out.values() if v.size == 1][0].reshape(()))
        M = roi.crop_to_image(LANDMARK_SIZE)
        xy = raw[:, :2] @ M[:, :2].T + M[:, 2] - 0.5
        z = raw[:, 2] * roi.size / LANDMARK_SIZE
        return np.concatenate([xy, z[:, None]], 1), float(1.0 / (1.0 + np.exp(-logit)))

    def __call__(self, image: np.ndarray) -> FaceLandmarks | None:
        """The landmarks of the largest face in ``image`` (the actor nearest the camera), or None when no face is
        found (or it fails presence)."""
        dets = self.detect_faces(image)
        if not dets:
            return None
        det = max(dets, key=lambda d: float(np.prod(d.box[2:] - d.box[:2])))
        roi = roi_from_detection(det)
        pts, presence = self.landmarks_in_roi(image, roi)
        for _ in range(self.refine):
            if presence < self.min_presence:
                break
            roi = roi_from_landmarks(pts)
            pts, presence = self.landmarks_in_roi(image, roi)
        if presence < self.min_presence:
            return None
        return FaceLandmarks(pts, presence, roi, det)
