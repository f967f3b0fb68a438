"""The motion measurements compared in the reproduction: semservo's and the baselines the
paper compared against (Table IV), each a function from (reference, current frame) to
the content's motion, so that every one closes the same loop (:mod:`.loop`).

Each ``measure(current) -> Measured`` gives the content displacement of the current
frame against the reference (x right, y down, pixels; rotation counter-clockwise, as
:mod:`semservo.estimation`), or ``ok=False`` with the reason when the method has lost the
scene (too few matches, a flow that is not one motion, a diverging photometric error).

Settings, chosen sensibly once and documented here (not tuned per case):

* ``photometric``: direct visual servoing on the luminance (Collewet and Marchand 2011;
  Tamadazte, Le Fort-Piat, Marchand 2012; ViSP's vpFeatureLuminance), as its authors run
  it: the error is I - I* normalised to zero mean and unit spread (the SEM's brightness
  drifts), the interaction matrix from the reference's gradients (translation:
  L = -grad I*), one Levenberg-Marquardt step (H + mu diag H)^-1 L^T e per frame, the
  damping mu halved while the cost falls and quadrupled when it rises (gradient descent
  far away, Gauss-Newton near), coarse to fine on an image pyramid (frames halved 4, 3
  then 2 times: a level hands over to the finer one once its step has stayed under a
  tenth of its pixel for three frames). ``photometric_single`` is the earlier setting (one level, halved twice, mu 1).
* ``dis``, ``farneback``: OpenCV's dense optical flow (DIS preset MEDIUM; Farneback
  pyramid 0.5, 4 levels, window 21), coarse to fine: on the frames halved three times,
  then (the frame moved back by that) halved twice; the motion is the median flow,
  refused when the flow is not one motion (its median spread about the median over 2 px
  at the fine scale). The starts are up to 77 px away, beyond either flow's reach at
  full resolution.
* ``sift``, ``orb``: OpenCV's SIFT (the patent-free stand-in for the paper's SURF, which
  current OpenCV builds no longer include) and ORB (oriented FAST; the paper's FAST),
  ratio-test matches, a RANSAC similarity (cv2.estimateAffinePartial2D); at least 8
  inliers or the scene is lost.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from semservo.estimation import MotionEstimator

#: Method names, in the order tables list them.
METHODS = ("semservo", "photometric", "dis", "farneback", "sift", "orb")
LABELS = {"semservo": "semservo (Fourier)", "photometric": "photometric DVS", "dis": "flow: DIS",
          "farneback": "flow: Farneback", "sift": "SIFT (for SURF)", "orb": "ORB (for FAST)"}


@dataclass(frozen=True)
class Measured:
    dx: float
    dy: float
    rotation_deg: float
    ok: bool
    reason: str = ""
    compute_ms: float = 0.0


def _normalised(image: np.ndarray, halvings: int) -> np.ndarray:
    out = np.asarray(image, dtype=np.float32)
    for _ in range(halvings):
        out = cv2.pyrDown(out)
    return (out - out.mean()) / max(float(out.std()), 1e-6)


def semservo_method(reference: np.ndarray, rotation: bool = False, mask=None, scan_averaged: bool = False,
                    vibration_hz: tuple[float, ...] = (), line_time_s: float | None = None) -> Callable:
    estimator = MotionEstimator(reference, rotation=rotation, mask=mask, scan_averaged=scan_averaged)
    estimator.vibration_hz = tuple(vibration_hz) if estimator.scan_averaged else ()

    def measure(current: np.ndarray, first_row: int = 0) -> Measured:
        motion = estimator.estimate(current, first_row=first_row, line_time_s=line_time_s)
        ok = motion.confidence >= 0.5
        return Measured(motion.dx, motion.dy, motion.rotation_deg, ok, "" if ok else "low confidence")
    return measure


#: The photometric pyramid: frames halved this many times, coarsest first; a level hands
#: over once its step stays under this (its own pixels).
PHOTOMETRIC_LEVELS = (4, 3, 2)
HANDOVER_STEP = 0.1


def _photometric_level(reference: np.ndarray, halvings: int) -> dict:
    desired = _normalised(reference, halvings)
    grad_y, grad_x = np.gradient(desired)
    # Content moved by t: I(p) = I*(p - t), so dI/dt = -grad I*.
    interaction = -np.column_stack([grad_x.ravel(), grad_y.ravel()])
    return {"halvings": halvings, "desired": desired, "interaction": interaction,
            "hessian": interaction.T @ interaction,
            "initial_cost": float((desired ** 2).sum()) * 2}  # two unrelated images' e'e


def photometric_method(reference: np.ndarray, levels: tuple[int, ...] = PHOTOMETRIC_LEVELS,
                       adaptive_damping: bool = True) -> Callable:
    """Photometric DVS (module docstring): a Levenberg-Marquardt step per frame, coarse to fine."""
    pyramid = [_photometric_level(reference, halvings) for halvings in levels]
    state = {"level": 0, "damping": 1.0, "cost": None}

    def measure(current: np.ndarray) -> Measured:
        level = pyramid[state["level"]]
        error = (_normalised(current, level["halvings"]) - level["desired"]).ravel()
        cost = float(error @ error)
        if cost > 1.5 * level["initial_cost"]:
            return Measured(0.0, 0.0, 0.0, False, "photometric error beyond that of two unrelated images")
        if adaptive_damping and state["cost"] is not None:
            state["damping"] = float(np.clip(state["damping"] * (0.5 if cost < state["cost"] else 4.0), 1e-3, 1e2))
        state["cost"] = cost
        hessian = level["hessian"]
        step = -np.linalg.solve(hessian + state["damping"] * np.diag(np.diag(hessian)), level["interaction"].T @ error)
        scale = 2 ** level["halvings"]
        # Converged at this level (a step under a tenth of its pixel three frames running):
        # the finer level takes over.
        state["still"] = state.get("still", 0) + 1 if math.hypot(*step) < HANDOVER_STEP else 0
        if state["still"] >= 3 and state["level"] < len(pyramid) - 1:
            state.update(level=state["level"] + 1, cost=None, still=0)
        # The LM step is the content displacement's estimate; where the images differ by
        # more than the gradients' reach it is short and, far away, wrong: what DVS does.
        return Measured(float(-step[0] * scale), float(-step[1] * scale), 0.0, True)
    return measure


#: Dense flow on frames halved twice (and three times for the coarse step): the starts are
#: up to 15 % of the field away (77 px), beyond what either flow follows at full resolution.
FLOW_HALVINGS = 2


def _eight_bit_halved(image: np.ndarray, halvings: int) -> np.ndarray:
    out = cv2.normalize(image.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX)
    for _ in range(halvings):
        out = cv2.pyrDown(out)
    return out.astype(np.uint8)


def flow_method(reference: np.ndarray, kind: str) -> Callable:
    """Median dense flow, coarse to fine: first on frames halved three times (a long
    reach), then, the frame moved back by that, on frames halved twice (precision)."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM) if kind == "dis" else None
    desired = {halvings: _eight_bit_halved(reference, halvings) for halvings in (FLOW_HALVINGS, FLOW_HALVINGS + 1)}

    def median_flow(frame: np.ndarray, halvings: int) -> tuple[float, float, float]:
        current = _eight_bit_halved(frame, halvings)
        if dis is not None:
            flow = dis.calc(desired[halvings], current, None)
        else:
            flow = cv2.calcOpticalFlowFarneback(desired[halvings], current, None, 0.5, 4, 21, 3, 5, 1.1, 0)
        dx, dy = float(np.median(flow[..., 0])), float(np.median(flow[..., 1]))
        spread = float(np.median(np.hypot(flow[..., 0] - dx, flow[..., 1] - dy)))
        return dx * 2 ** halvings, dy * 2 ** halvings, spread

    def measure(current: np.ndarray) -> Measured:
        coarse_x, coarse_y, _ = median_flow(current, FLOW_HALVINGS + 1)
        if not np.isfinite([coarse_x, coarse_y]).all():
            return Measured(0.0, 0.0, 0.0, False, "no coarse flow")
        back = np.float32([[1, 0, -coarse_x], [0, 1, -coarse_y]])
        moved_back = cv2.warpAffine(current.astype(np.float32), back, current.shape[::-1], borderMode=cv2.BORDER_REFLECT)
        fine_x, fine_y, spread = median_flow(moved_back, FLOW_HALVINGS)
        if not np.isfinite([fine_x, fine_y]).all() or spread > 2.0:
            return Measured(0.0, 0.0, 0.0, False, f"the flow is not one motion (median spread {spread:.1f} px)")
        return Measured(coarse_x + fine_x, coarse_y + fine_y, 0.0, True)
    return measure


def keypoint_method(reference: np.ndarray, kind: str) -> Callable:
    detector = cv2.SIFT_create(nfeatures=1500) if kind == "sift" else cv2.ORB_create(nfeatures=1500, fastThreshold=10)
    norm = cv2.NORM_L2 if kind == "sift" else cv2.NORM_HAMMING
    matcher = cv2.BFMatcher(norm)
    eight = cv2.normalize(reference.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    reference_points, reference_descriptors = detector.detectAndCompute(eight, None)
    centre = (np.array(reference.shape[::-1]) - 1) / 2

    def measure(current: np.ndarray) -> Measured:
        frame = cv2.normalize(current.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
        points, descriptors = detector.detectAndCompute(frame, None)
        if descriptors is None or reference_descriptors is None or len(points) < 8:
            return Measured(0.0, 0.0, 0.0, False, "too few keypoints")
        pairs = [m for m, n in (p for p in matcher.knnMatch(reference_descriptors, descriptors, k=2) if len(p) == 2)
                 if m.distance < 0.75 * n.distance]
        if len(pairs) < 8:
            return Measured(0.0, 0.0, 0.0, False, f"{len(pairs)} matches pass the ratio test")
        source = np.float32([reference_points[m.queryIdx].pt for m in pairs])
        target = np.float32([points[m.trainIdx].pt for m in pairs])
        matrix, inliers = cv2.estimateAffinePartial2D(source, target, method=cv2.RANSAC, ransacReprojThreshold=2.0)
        if matrix is None or int(inliers.sum()) < 8:
            return Measured(0.0, 0.0, 0.0, False, "no similarity with 8 inliers")
        moved_centre = matrix[:, :2] @ centre + matrix[:, 2]
        # Counter-clockwise as displayed (y down): the matrix turns by -angle.
        angle = -math.degrees(math.atan2(matrix[1, 0], matrix[0, 0]))
        return Measured(float(moved_centre[0] - centre[0]), float(moved_centre[1] - centre[1]), angle, True)
    return measure


def make(name: str, reference: np.ndarray, *, rotation: bool = False, mask=None,
         scan_averaged: bool = False, vibration_hz: tuple[float, ...] = (),
         line_time_s: float | None = None) -> Callable[[np.ndarray], Measured]:
    """The method ``name`` taught ``reference``; its measure() is timed. ``scan_averaged``:
    semservo's shift averaged over the scan's bands of rows, as its estimator service
    measures live frames (the paper's tables use the whole-frame estimate, eq. 18-24);
    with ``vibration_hz`` (learned at the teach) and the scan's ``line_time_s``, over the
    scan's time by fitting those vibration lines."""
    if name == "semservo":
        inner = semservo_method(reference, rotation, mask, scan_averaged, vibration_hz, line_time_s)
    elif name == "photometric":
        inner = photometric_method(reference)
    elif name == "photometric_single":
        inner = photometric_method(reference, levels=(2,), adaptive_damping=False)
    elif name in ("dis", "farneback"):
        inner = flow_method(reference, name)
    elif name in ("sift", "orb"):
        inner = keypoint_method(reference, name)
    else:
        raise ValueError(f"unknown method {name!r}; methods: {', '.join(METHODS)}")

    def timed(current: np.ndarray, first_row: int = 0) -> Measured:
        started = time.perf_counter()
        result = inner(current, first_row) if first_row else inner(current)
        return Measured(result.dx, result.dy, result.rotation_deg, result.ok, result.reason,
                        (time.perf_counter() - started) * 1e3)
    return timed
