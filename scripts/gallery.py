"""Write a PNG of every simulated preset, still and while the stage moves, plus the
piezo hysteresis loop, into docs/gallery/ (the README shows a few).

With ``--sample-image FILE`` instead: how the simulated SEM sees a real picture as its
sample (semservo.simulation.sample_image) - the picture as read, a frame at its scale,
one with the stage moving during the scan, one tilted in the small depth of field of the
``tilts`` preset, and one beyond the picture's edges - as one PNG in ``--out``. (The
real pictures in ../shared/data are not copied into the repository, nor are frames of
them: write these to a folder of your own.)

    .venv/bin/python scripts/gallery.py [--out docs/gallery]
    .venv/bin/python scripts/gallery.py --sample-image my.tif [--sample-pixel-nm 50] --out /tmp/look
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


def sample_image_frames(args) -> Path:
    """A real picture through the simulated SEM: as read, a frame, moving, tilted, at its edge."""
    from semservo.simulation.sample_image import SampleImage
    from semservo.simulation.world import World

    sample = SampleImage.open(args.sample_image, pixel_size_nm=args.sample_pixel_nm, edges=args.sample_edges)
    panels = []
    rows, cols = sample.shape
    crop = sample.intensity[max(0, rows // 2 - 256): rows // 2 + 256, max(0, cols // 2 - 256): cols // 2 + 256]
    picture = np.zeros((512, 512), np.uint8)
    picture[:crop.shape[0], :crop.shape[1]] = np.clip(crop * 255, 0, 255).astype(np.uint8)
    panels.append(labelled(picture, f"{sample.name}: as read, denoised ({sample.pixel_um * 1000:.4g} nm/px)"))
    rng = np.random.default_rng(1)
    for preset_name, caption, poses in (
            ("optimal", "optimal: a frame", lambda field: ([Pose()] * 512, [Pose()] * 512)),
            ("optimal", "stage moving during the scan", lambda field: (
                [Pose(x_um=0.3 * field * r / 512) for r in range(512)],
                [Pose(x_um=0.3 * field * (r + 1) / 512) for r in range(512)])),
            ("tilts", "tilts preset: alpha 4 deg", lambda field: ([Pose(tilt_x_deg=4.0)] * 512,) * 2),
            ("optimal", f"{sample.edges} beyond the edge", lambda field: (
                [Pose(x_um=0.45 * sample.size_um[0], y_um=0.45 * sample.size_um[1])] * 512,) * 2)):
        world = World(PRESETS[preset_name], sample_image=sample)
        settings = ScanSettings(dwell_ns=world.preset.dwell_ns, magnification=world.preset.magnification,
                                working_distance_um=world.preset.focus_um)
        start, end = poses(settings.pixel_um * 512)
        panels.append(labelled(world.sem.render(settings, start, end, rng), caption))
    sheet = Image.new("L", (512 * len(panels), 512))
    for index, panel in enumerate(panels):
        sheet.paste(panel, (512 * index, 0))
    path = args.out / f"sample-{Path(args.sample_image).stem}.png"
    sheet.save(path, optimize=True)
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "gallery")
    parser.add_argument("--sample-image", type=Path, help="a real picture: show it through the simulated SEM")
    parser.add_argument("--sample-pixel-nm", type=float, help="its pixel size (default: its metadata)")
    parser.add_argument("--sample-edges", choices=["mirror", "tile", "pad"], default="mirror")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.sample_image:
        from semservo.simulation.sample_image import SampleImageError

        try:
            print(f"wrote {sample_image_frames(args)}")
        except SampleImageError as error:
            print(f"gallery: sample image refused: {error}", file=sys.stderr)
            return 2
        return 0
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
