"""Test pairs with exactly known motion, made from real SEM frames.

Sub-pixel shifts, without interpolation: take a real frame, cut two windows ``factor * shift`` pixels apart
(integers at full resolution), and block-average each by ``factor``: the two results
are the same scene shifted by exactly ``shift`` pixels (halves, thirds, quarters, ...),
with genuinely new content entering at the borders, as on a moving stage.

Turns and moves of the view (:func:`turned_and_moved`): a real frame turned about its centre
and moved, with the content that enters taken from the rest of the image.

Used by ``bench/estimator.py``, ``bench/sem_images.py`` and the tests; useful to check an
estimator on your own frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def block_average(image: np.ndarray, factor: int) -> np.ndarray:
    """Exact mean of ``factor`` x ``factor`` blocks, in float64 (no interpolation)."""
    rows, cols = (image.shape[0] // factor) * factor, (image.shape[1] // factor) * factor
    return image[:rows, :cols].astype(np.float64).reshape(rows // factor, factor, cols // factor, factor).mean(axis=(1, 3))


@dataclass(frozen=True)
class ShiftedPair:
    reference: np.ndarray
    current: np.ndarray
    dx: float
    dy: float


def shifted_pair(frame: np.ndarray, dx: float, dy: float, factor: int, margin: int | None = None) -> ShiftedPair:
    """Reference and current (content moved by exactly (dx, dy) px) from one frame.

    ``dx * factor`` and ``dy * factor`` must be integers. The windows are cut ``margin``
    full-resolution pixels in from the frame's edges (default: enough for the shift).
    """
    step_x, step_y = dx * factor, dy * factor
    if abs(step_x - round(step_x)) > 1e-9 or abs(step_y - round(step_y)) > 1e-9:
        raise ValueError(f"shift ({dx}, {dy}) is not a multiple of 1/{factor}")
    step_x, step_y = int(round(step_x)), int(round(step_y))
    margin = margin if margin is not None else max(abs(step_x), abs(step_y))
    rows, cols = frame.shape
    if max(abs(step_x), abs(step_y)) > margin:
        raise ValueError(f"a shift of {max(abs(step_x), abs(step_y))} full-resolution pixels needs margin >= that")
    height, width = rows - 2 * margin, cols - 2 * margin
    height, width = (height // factor) * factor, (width // factor) * factor
    reference = frame[margin:margin + height, margin:margin + width]
    # current[y, x] == reference[y - dy, x - dx]: the window moves the other way.
    current = frame[margin - step_y:margin - step_y + height, margin - step_x:margin - step_x + width]
    return ShiftedPair(block_average(reference, factor), block_average(current, factor), dx, dy)


def poisson_gaussian(image: np.ndarray, electrons: float, read_sigma: float, rng: np.random.Generator) -> np.ndarray:
    """SEM-like noise: Poisson counts of ``electrons`` per unit grey level at full scale,
    plus Gaussian amplifier noise (grey levels)."""
    scale = electrons / 255.0
    counts = rng.poisson(np.clip(image, 0, None) * scale) / scale
    return (counts + rng.normal(0, read_sigma, image.shape)).astype(np.float32)


def centred_window(image: np.ndarray, side: int) -> np.ndarray:
    """The centred ``side`` x ``side`` window of ``image`` (float32)."""
    return turned_and_moved(image, side, 0.0, 0.0, 0.0)


def turned_and_moved(image: np.ndarray, side: int, angle_deg: float, dx: float, dy: float) -> np.ndarray:
    """What a frame shows after a turn and a move of the view: the content of the centred
    ``side`` x ``side`` window of ``image`` turned by ``angle_deg`` (counter-clockwise as
    displayed) about the window's centre, then moved by (dx, dy) px (right, down), in the
    sign convention of :mod:`semservo.estimation` (so its estimate against
    :func:`centred_window` is exactly (dx, dy, angle_deg)). New content enters from the
    rest of the image, which is mirrored where the view runs beyond it. Bicubic."""
    import cv2

    rows, cols = image.shape
    image_centre = np.array([(cols - 1) / 2, (rows - 1) / 2])
    frame_centre = np.array([(side - 1) / 2, (side - 1) / 2])
    theta = np.radians(angle_deg)
    turn = np.array([[np.cos(theta), np.sin(theta)], [-np.sin(theta), np.cos(theta)]])
    # A frame pixel p shows the image at image_centre + turn^-1 (p - frame_centre - d).
    back = turn.T
    matrix = np.hstack([back, (image_centre - back @ (frame_centre + np.array([dx, dy])))[:, None]])
    return cv2.warpAffine(np.asarray(image, dtype=np.float32), matrix, (side, side),
                          flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)
