"""Write a PNG of every simulated preset, still and while the stage moves, plus the
piezo hysteresis loop, into docs/gallery/ (the README shows a few).

    .venv/bin/python scripts/gallery.py [--out docs/gallery]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from semservo.simulation.piezo import PiezoAxis, voltage_for
from semservo.simulation.sem import SEM, Pose, ScanSettings
from semservo.simulation.world import PRESETS


def labelled(pixels: np.ndarray, text: str) -> Image.Image:
    image = Image.fromarray(pixels)
    draw = ImageDraw.Draw(image)
    draw.rectangle([0, 0, 8 + 6 * len(text), 14], fill=0)
    draw.text((4, 2), text, fill=255)
    return image


def preset_frames(name: str) -> tuple[Image.Image, Image.Image]:
    preset = PRESETS[name]
    sem = SEM(preset.scene)
    settings = ScanSettings(dwell_ns=preset.dwell_ns, magnification=preset.magnification)
    rng = np.random.default_rng(1)
    still = sem.render(settings, [Pose()] * 512, [Pose()] * 512, rng)
    # The stage moving 40 % of the field to the right and 15 % down during the scan:
    # sheared, stretched content (the paper's Fig. 1).
    field_um = settings.pixel_um * 512
    start = [Pose(x_um=0.4 * field_um * row / 512, y_um=0.15 * field_um * row / 512) for row in range(512)]
    end = [Pose(x_um=0.4 * field_um * (row + 1) / 512, y_um=0.15 * field_um * (row + 1) / 512) for row in range(512)]
    moving = sem.render(settings, start, end, rng)
    caption = f"{name}: x{preset.magnification:g}, {preset.dwell_ns:g} ns/px"
    return labelled(still, caption), labelled(moving, caption + ", stage moving")


def hysteresis_plot(path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for axis_name, ax in zip("xy", axes):
        axis = PiezoAxis(axis_name)
        for low, high, style in ((-19, 96, "-"), (20, 60, "--"), (35, 45, ":")):
            volts = np.linspace(low, high, 200)
            for _ in range(2):
                rising = [axis.hysteresis.apply(v) for v in volts]
                falling = [axis.hysteresis.apply(v) for v in volts[::-1]]
            ax.plot(volts, rising, style, color="tab:red", label=f"model {low}..{high} V")
            ax.plot(volts[::-1], falling, style, color="tab:blue")
        displacement = np.linspace(0, 100, 100)
        ax.plot(voltage_for(axis_name, "increasing", displacement), displacement, color="k", lw=0.8, alpha=0.5,
                label="lab model, increasing")
        ax.plot(voltage_for(axis_name, "decreasing", displacement), displacement, color="gray", lw=0.8,
                alpha=0.5, label="lab model, decreasing")
        ax.set_xlabel("voltage (V)")
        ax.set_ylabel(f"{axis_name} displacement (um)")
        ax.set_title(f"TRITOR {axis_name}: hysteresis of the emulated stage")
        ax.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=100)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "gallery")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for name in PRESETS:
        still, moving = preset_frames(name)
        still.save(args.out / f"{name}.png", optimize=True)
        moving.save(args.out / f"{name}-moving.png", optimize=True)
        print(f"wrote {name}.png and {name}-moving.png", flush=True)
    hysteresis_plot(args.out / "hysteresis.png")
    print(f"wrote hysteresis.png to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
