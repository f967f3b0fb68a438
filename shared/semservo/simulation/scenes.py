"""Samples: what the beam sees, as secondary-electron yield and height maps.

Each scene is defined in micrometres (feature sizes do not depend on magnification) and
rasterized once per sampling grid, seeded and reproducible, over a region larger than
any field of view. The secondary-electron look follows ``shared/reference/sem-imaging.md``
(after Cizmar et al., Scanning 2008): inside a feature the yield rises towards its edge,
I = a exp(-b d) + c with d the distance to the edge; small random disks scale the yield
by 0.95-1.05 (fine structure); the background carries a smooth random texture.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

SCENES = ("micropart", "gold-on-carbon", "crosses", "chessboard", "gripper")


@dataclass(frozen=True)
class Sample:
    """A rasterized scene: yield (0..1) and height (um) on a square grid centred on the
    sample origin; grid pixel (row, col) is at ((col + 0.5) * pixel_um - extent_um / 2,
    (row + 0.5) * pixel_um - extent_um / 2) um."""

    name: str
    intensity: np.ndarray
    height_um: np.ndarray
    pixel_um: float
    extent_um: float

    def to_grid(self, x_um, y_um):
        """Grid coordinates (col, row) of sample coordinates in um (for cv2.remap)."""
        offset = self.extent_um / 2 / self.pixel_um - 0.5
        return x_um / self.pixel_um + offset, y_um / self.pixel_um + offset


class _Canvas:
    """Draws shapes given in um onto a grid mask."""

    def __init__(self, size: int, pixel_um: float, extent_um: float):
        self.size, self.pixel_um, self.extent_um = size, pixel_um, extent_um
        self.shift = 4  # cv2 sub-pixel drawing: 1/16 px

    def points(self, xy_um) -> np.ndarray:
        xy = (np.asarray(xy_um, dtype=np.float64) + self.extent_um / 2) / self.pixel_um - 0.5
        return np.round(xy * (1 << self.shift)).astype(np.int32)

    def polygon(self, mask: np.ndarray, xy_um, value: int = 255) -> None:
        cv2.fillPoly(mask, [self.points(xy_um)], value, lineType=cv2.LINE_AA, shift=self.shift)

    def disk(self, mask: np.ndarray, centre_um, radius_um: float, value: int = 255) -> None:
        centre = tuple(int(v) for v in self.points(centre_um))
        radius = int(round(radius_um / self.pixel_um * (1 << self.shift)))
        cv2.circle(mask, centre, max(radius, 1), value, -1, lineType=cv2.LINE_AA, shift=self.shift)


def _smooth_texture(size: int, rng: np.random.Generator, cells: int, amplitude: float) -> np.ndarray:
    coarse = rng.normal(0.0, amplitude, (cells, cells)).astype(np.float32)
    return cv2.resize(coarse, (size, size), interpolation=cv2.INTER_CUBIC)


def _edge_brightened(mask: np.ndarray, pixel_um: float, base: float, a: float = 0.3, b_per_um: float = 1.5) -> np.ndarray:
    """Yield inside a feature mask: base + a exp(-b d), d the distance to the edge (um)."""
    inside = (mask > 127).astype(np.uint8)
    distance_um = cv2.distanceTransform(inside, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * pixel_um
    return (base + a * np.exp(-b_per_um * distance_um)).astype(np.float32)


def _compose(canvas: _Canvas, rng: np.random.Generator, background: float, features: list,
             texture_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Background texture, then features (mask, base yield, height um) with edge effect,
    then fine structure."""
    size, pixel = canvas.size, canvas.pixel_um
    intensity = background + _smooth_texture(size, rng, texture_cells, 0.04)
    height = np.zeros((size, size), np.float32)
    for mask, base, feature_height in features:
        weight = mask.astype(np.float32) / 255.0
        brightened = _edge_brightened(mask, pixel, base)
        intensity = intensity * (1 - weight) + brightened * weight
        height = height * (1 - weight) + feature_height * weight
    # Fine structure: small disks that scale the yield by 0.95..1.05.
    fine = np.ones((size, size), np.float32)
    count = int(0.02 * size * size / max(1.0, (0.08 / pixel) ** 2))
    centres = rng.uniform(0, size, (min(count, 200_000), 2)).astype(np.int32)
    radii = np.maximum(1, rng.uniform(0.02, 0.08, len(centres)) / pixel).astype(np.int32)
    scales = rng.uniform(0.95, 1.05, len(centres))
    for (x, y), radius, scale in zip(centres, radii, scales):
        cv2.circle(fine, (int(x), int(y)), int(radius), float(scale), -1)
    return np.clip(intensity * fine, 0.0, 1.0).astype(np.float32), height


def rasterize(name: str, pixel_um: float, extent_um: float, seed: int = 2013) -> Sample:
    """The scene ``name`` on a grid of ``pixel_um`` covering ``extent_um`` square."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; scenes: {', '.join(SCENES)}")
    size = int(np.ceil(extent_um / pixel_um))
    extent_um = size * pixel_um
    canvas = _Canvas(size, pixel_um, extent_um)
    rng = np.random.default_rng(seed)
    half = extent_um / 2
    features = []

    def new_mask() -> np.ndarray:
        return np.zeros((size, size), np.uint8)

    if name == "micropart":
        # A 10 um wide silicon bar (500 um long: longer than any field), 10 um tall,
        # turned 20 degrees, with etch holes and a notch so motion along it is visible.
        bar = new_mask()
        angle = np.deg2rad(20)
        along, across = np.array([np.cos(angle), np.sin(angle)]), np.array([-np.sin(angle), np.cos(angle)])
        corners = [s * 250 * along + t * 5 * across for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        canvas.polygon(bar, corners)
        for position in np.arange(-240, 241, 13.0):
            if rng.random() < 0.8:
                canvas.disk(bar, position * along + rng.uniform(-2, 2) * across, rng.uniform(0.8, 1.8), 0)
        notch = [p * along + q * across for p, q in ((6, 5.5), (14, 5.5), (11, 2.5))]
        canvas.polygon(bar, notch, 0)
        features.append((bar, 0.42, 10.0))
        # Debris on the substrate.
        debris = new_mask()
        for _ in range(int(extent_um**2 / 60)):
            canvas.disk(debris, rng.uniform(-half, half, 2), rng.uniform(0.2, 0.9))
        features.insert(0, (debris, 0.5, 0.3))
        intensity, height = _compose(canvas, rng, 0.22, features, texture_cells=max(8, int(extent_um / 6)))
    elif name == "gold-on-carbon":
        grains = new_mask()
        for _ in range(int(extent_um**2 / 6)):
            centre = rng.uniform(-half, half, 2)
            radius = rng.gamma(2.0, 0.25) + 0.1
            angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
            wobble = 1 + sum(rng.normal(0, 0.08) * np.cos(k * angles + rng.uniform(0, 6.3)) for k in (2, 3, 5))
            canvas.polygon(grains, centre + radius * wobble[:, None] * np.c_[np.cos(angles), np.sin(angles)])
        features.append((grains, 0.6, 0.2))
        intensity, height = _compose(canvas, rng, 0.2, features, texture_cells=max(8, int(extent_um / 3)))
    elif name == "crosses":
        crosses = new_mask()
        pitch = 8.0
        for cx in np.arange(-half, half + pitch, pitch):
            for cy in np.arange(-half, half + pitch, pitch):
                for w, h in ((2.5, 0.6), (0.6, 2.5)):
                    canvas.polygon(crosses, [(cx - w, cy - h), (cx + w, cy - h), (cx + w, cy + h), (cx - w, cy + h)])
        features.append((crosses, 0.55, 0.5))
        intensity, height = _compose(canvas, rng, 0.3, features, texture_cells=max(8, int(extent_um / 4)))
    elif name == "chessboard":
        # Gold on silicon calibration pattern: 4 um squares, a few defects.
        board = new_mask()
        square = 4.0
        for ix, cx in enumerate(np.arange(-half, half + square, square)):
            for iy, cy in enumerate(np.arange(-half, half + square, square)):
                if (ix + iy) % 2 == 0:
                    canvas.polygon(board, [(cx, cy), (cx + square, cy), (cx + square, cy + square), (cx, cy + square)])
        for _ in range(int(extent_um**2 / 400)):
            canvas.disk(board, rng.uniform(-half, half, 2), rng.uniform(0.3, 1.0), int(rng.choice([0, 255])))
        features.append((board, 0.65, 0.1))
        intensity, height = _compose(canvas, rng, 0.3, features, texture_cells=max(8, int(extent_um / 4)))
    else:  # gripper: two fingers with a notch between them, as in the recorded run
        gripper = new_mask()
        outline = [(-30, -35), (-22, -36), (-12, 5), (-4, 5), (-4, 2), (4, 2), (4, 5), (12, 5), (22, -36),
                   (30, -35), (32, 30), (20, 42), (-20, 42), (-32, 30)]
        canvas.polygon(gripper, [(x, y) for x, y in outline])
        features.append((gripper, 0.32, 20.0))
        intensity, height = _compose(canvas, rng, 0.55, features, texture_cells=max(8, int(extent_um / 5)))
    return Sample(name, intensity, height, pixel_um, extent_um)
