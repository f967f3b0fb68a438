"""Mask references (the paper's case 6): the reference made a two-level mask image.
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np
from PIL import Image, ImageDraw


def polygon_mask(shape: tuple[int, int], corners: Sequence[Sequence[float]]) -> np.ndarray:
    """Boolean mask of ``shape`` that is True inside the polygon of (x, y) corners."""
    if len(corners) < 3:
        raise ValueError(f"a polygon needs at least 3 corner points, got {len(corners)}")
    points = [(float(x), float(y)) for x, y in corners]
    canvas = Image.new("1", (shape[1], shape[0]), 0)
    ImageDraw.Draw(canvas).polygon(points, fill=1, outline=1)
    return np.asarray(canvas, dtype=bool)


#: A mask image is two levels; its edges may be antialiased, so this share of its pixels
#: at its darkest or brightest level is enough.
MIN_BINARY_SHARE = 0.95


def binary_region(mask: np.ndarray, name: str = "the mask") -> np.ndarray:
    """The object of a mask image (paper case 6: the object bright on dark), as a boolean
    array: the pixels above the middle of its two levels. ValueError when the image is not
    two levels (a grey picture given as a mask would make a meaningless reference)."""
    values = np.asarray(mask, dtype=np.float64)
    if values.ndim != 2 or not np.all(np.isfinite(values)):
        raise ValueError(f"{name} must be a 2-D image of finite grey levels")
    low, high = float(values.min()), float(values.max())
    at_either = np.count_nonzero((values == low) | (values == high)) / values.size
    if high == low or at_either < MIN_BINARY_SHARE:
        raise ValueError(f"{name} is not binary: {at_either:.0%} of its pixels are at its darkest or brightest level "
                         f"(at least {MIN_BINARY_SHARE:.0%} needed: the object white on black)")
    return values > (low + high) / 2


def mask_reference(reference: np.ndarray, mask) -> np.ndarray:
    """The two-level image that stands in for a taught reference (paper case 6).

    ``mask`` is a boolean array of the reference's shape or a list of (x, y) polygon
    corners. Inside and outside take the reference's mean grey levels there, so the
    mask has the scene's polarity (phase correlation needs it); its edges are softened
    by a 1-pixel Gaussian, like the probe blur of a real image.
    """
    if isinstance(mask, np.ndarray) and mask.ndim == 2:
        if mask.shape != reference.shape:
            raise ValueError(f"mask is {mask.shape}, reference is {reference.shape}")
        region = mask.astype(bool)
    else:
        region = polygon_mask(reference.shape, mask)
    if region.all() or not region.any():
        raise ValueError("the mask must cover part of the image, not none or all of it")
    inside = float(reference[region].mean())
    outside = float(reference[~region].mean())
    if inside == outside:
        inside, outside = 1.0, 0.0
    two_level = np.where(region, inside, outside).astype(np.float32)
    return cv2.GaussianBlur(two_level, (0, 0), 1.0)
