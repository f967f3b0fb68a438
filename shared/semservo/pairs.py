"""Test pairs with exactly known motion, made from real SEM frames without interpolation.

Sub-pixel shifts: take a real frame, cut two windows ``factor * shift`` pixels apart
(integers at full resolution), and block-average each by ``factor``: the two results
are the same scene shifted by exactly ``shift`` pixels (halves, thirds, quarters, ...),
with genuinely new content entering at the borders, as on a moving stage.

Used by ``bench/estimator.py`` and the tests; useful to check an estimator on your own frames.
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
