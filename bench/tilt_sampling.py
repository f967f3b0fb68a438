"""Where the focus falls between a sweep's samples: the tilts' bias that no noise causes,
per real texture, defocus model and focus measure.

Each kernel's depth is read between the samples of its focus curve, and the reading is
pulled by a fraction of a step that depends on where the curve's peak falls between
them (its phase) and on the curve's shape (the kernel's content). The estimator keeps a
floor for it in every tilt's standard error (``SAMPLING_BIAS_STEPS`` of a step over the
span of the kernels used) and sweeps a run's poses on the taught sweep's working
distances (``plan_sweep(..., grid=...)``), so that at the taught pose the bias is the
teach's own and cancels. This bench measures both assumptions on noise-free sweeps (the
same scenes as ``bench/tilt_real.py``: 512 px over 25 um, 21 working distances planned
for a depth of field of 2.5 um, both defocus models), with the taught (flat) view's
working distances moved by ``--phases`` fractions of a step. Each noise-free sweep is
read as its noisy twin at the benchmark's dose would be (``--electrons``, 1000 per grey
level at full scale; ``depths_from_curves``): the noise-free curves with the twin's noise
share, so that the same kernels pass the clear-peak test, the same of the two readings
(the mirror, the fitted curve) reads each, and they weigh alike; what is left is the
pull, not the noise. ``--electrons 0``: noise-free throughout (every kernel, read by the
mirror where the two readings tie).

* **taught view**: the largest |alpha|, |beta| the flat view reads over the phases (its
  truth is 0): what an absolute tilt carries;
* **against the teach**: for poses 0.18-14 degrees from it, swept on the taught view's
  working distances, the largest |error| over the phases of the pose's reading less the
  taught one's: what a measurement in a run or in Table I carries;
* **floor**: the standard error the estimator claims for a pose read so (the
  ``SAMPLING_BIAS_STEPS`` floor, and what the jackknife over the kernels adds where they
  are few), the median over the phases.

Only the readings the estimator accepts count (a refused one has no angles); how many
were refused is kept in the results (``refused``, per pose, of ``--phases``).

A bias above the floor is an error the estimate does not own up to. Writes
bench/results/tilt_sampling.json and .png (the errors against the tilt from the teach,
per defocus model and focus measure, a line per image, the floor dashed).

    ./dev bench tilt_sampling                           # all six images, both models, 8 phases
    ./dev bench tilt_sampling --images jeol_grid --models disc --phases 4
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from tilt_real import (DEFAULT_MODELS, DEPTH_OF_FIELD_UM, ELECTRONS, FIELD_PX, FIELD_UM, READ_NOISE,  # noqa: E402
                       add_texture_arguments, read_textures)

from semservo import jsontext  # noqa: E402
from semservo.estimation.tilt import (FOCUS_MEASURES, SAMPLING_BIAS_STEPS, FocusCurves,  # noqa: E402
                                      depths_from_curves, focus_measure_curves, noise_free_focus_curves, plan_sweep,
                                      tilt_from_depths)
from semservo.focus_sweeps import DEFOCUS_SHAPES, DefocusModel, TiltedTexture  # noqa: E402
from semservo.pairs import poisson_gaussian  # noqa: E402
from semservo.reproduce import Progress  # noqa: E402

RESULTS = Path(__file__).parent / "results"
KERNEL = 32
FLAT = (0.0, 0.0, 0.0)
#: Poses (alpha, beta, gamma; degrees) 0.18-14 degrees of tilt from the taught view: the
#: plane spans from a fifth of a sweep step to five across the field.
POSES = ((0.15, -0.1, 0.0), (0.4, -0.3, 0.0), (0.8, 0.6, 5.0), (1.5, 1.0, 10.0), (2.5, -2.0, 15.0),
         (5.0, -3.0, 20.0), (12.0, 8.0, -40.0))


def with_noise_of(clean: FocusCurves, noisy: FocusCurves | None) -> FocusCurves:
    """``clean``'s curves with ``noisy``'s noise share (``clean`` alone without one)."""
    return clean if noisy is None else FocusCurves(clean.signal, noisy.noise, noisy.pixels)


def readings(sweep: np.ndarray, twin: np.ndarray | None) -> dict[str, tuple[FocusCurves, FocusCurves]]:
    """Per focus measure, the curves of the noise-free ``sweep`` as its noisy ``twin``
    would have them read (its noise share), and eq. 13's likewise (where each kernel's
    texture lies): each sweep's eq. 13 curves made once for both measures."""
    clean = noise_free_focus_curves(sweep, KERNEL)
    loud = None if twin is None else noise_free_focus_curves(twin, KERNEL)
    eq13 = with_noise_of(clean, loud)
    return {measure: (with_noise_of(focus_measure_curves(sweep, KERNEL, measure, clean),
                                    None if twin is None else focus_measure_curves(twin, KERNEL, measure, loud)), eq13)
            for measure in FOCUS_MEASURES}


def tilts(sweep: np.ndarray, curves: FocusCurves, eq13: FocusCurves, distances: np.ndarray):
    """The estimate of one noise-free ``sweep`` read from these ``curves`` (:func:`readings`;
    NaN angles where it is refused)."""
    pixel_um = FIELD_UM / FIELD_PX
    depths = depths_from_curves(sweep, curves, eq13, distances, KERNEL, pixel_um)
    return tilt_from_depths(depths.depths, KERNEL, pixel_um, float(distances[1] - distances[0]), depths.uncertainties)


def one_texture(texture: np.ndarray, shape: str, phases: int, electrons: float, seed: int, step) -> dict:
    """Per focus measure: the taught view's largest |alpha|, |beta| over the phases, and
    per pose the largest |error| against the teach, the median floor claimed and how
    many of the phases were refused (the taught view's or the pose's reading)."""
    model = DefocusModel(shape, depth_of_field_um=DEPTH_OF_FIELD_UM)
    scenes = {pose: TiltedTexture(texture, model, FIELD_UM / FIELD_PX, shape=(FIELD_PX, FIELD_PX), pose=pose)
              for pose in (FLAT, *POSES)}
    rng = np.random.default_rng(seed)
    planned = plan_sweep(0.0, DEPTH_OF_FIELD_UM, FIELD_UM)
    sweep_step = float(planned[1] - planned[0])
    taught = {measure: [] for measure in FOCUS_MEASURES}
    against = {measure: {pose: [] for pose in POSES} for measure in FOCUS_MEASURES}
    floors = {measure: {pose: [] for pose in POSES} for measure in FOCUS_MEASURES}
    for phase in np.arange(phases) / phases:
        distances = planned + phase * sweep_step  # the taught sweep, and every pose's on its grid
        sweeps = {pose: np.stack([scene.noiseless_frame(float(distance)) for distance in distances])
                  for pose, scene in scenes.items()}
        twins = {pose: (np.stack([poisson_gaussian(frame, electrons, READ_NOISE, rng) for frame in sweep])
                        if electrons > 0 else None) for pose, sweep in sweeps.items()}
        read = {pose: readings(sweep, twins[pose]) for pose, sweep in sweeps.items()}
        for measure in FOCUS_MEASURES:
            reference = tilts(sweeps[FLAT], *read[FLAT][measure], distances)
            taught[measure].append((reference.alpha_deg, reference.beta_deg))
            for pose in POSES:
                estimate = tilts(sweeps[pose], *read[pose][measure], distances)
                against[measure][pose].append((estimate.alpha_deg - reference.alpha_deg - pose[0],
                                               estimate.beta_deg - reference.beta_deg - pose[1]))
                floors[measure][pose].append(max(estimate.alpha_uncertainty_deg, estimate.beta_uncertainty_deg))
        step(f"phase {phase:.3f}")
    return {measure: {"taught": float(np.nanmax(np.abs(taught[measure]))),
                      "against": [float(np.nanmax(np.abs(against[measure][pose]))) for pose in POSES],
                      "floor": [float(np.nanmedian(floors[measure][pose])) for pose in POSES],
                      "refused": [int(np.isnan(against[measure][pose]).any(axis=1).sum()) for pose in POSES]}
            for measure in FOCUS_MEASURES}


def span(values) -> str:
    """'lowest-highest' to three decimals, one number where they agree."""
    low, high = f"{min(values):.3f}", f"{max(values):.3f}"
    return low if low == high else f"{low}-{high}"


def plot(results: dict[str, dict[str, dict]], path: Path) -> None:
    """The largest error against the teach over the phases, against the tilt from it: a
    panel per defocus model and focus measure, a line per image, its floor dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    magnitudes = [float(np.hypot(alpha, beta)) for alpha, beta, _ in POSES]
    shapes = list(results)
    figure, axes = plt.subplots(len(shapes), len(FOCUS_MEASURES), figsize=(5 * len(FOCUS_MEASURES), 3.4 * len(shapes)),
                                squeeze=False, sharex=True, sharey=True)
    for row, shape in enumerate(shapes):
        for col, measure in enumerate(FOCUS_MEASURES):
            axis = axes[row, col]
            for index, (name, reading) in enumerate(results[shape].items()):
                colour = f"C{index % 10}"
                axis.plot(magnitudes, reading[measure]["against"], "o-", color=colour, label=name, markersize=3)
                axis.plot(magnitudes, reading[measure]["floor"], "--", color=colour, linewidth=0.8)
            axis.set_xscale("log")
            axis.set_title(f"{shape} defocus, {'eq. 13' if measure == 'normalized_variance' else measure}", fontsize=9)
            axis.grid(True, which="both", alpha=0.3)
            if col == 0:
                axis.set_ylabel("largest |error| (degrees)")
            if row == len(shapes) - 1:
                axis.set_xlabel("tilt from the taught pose (degrees)")
    axes[0, 0].legend(fontsize=7)
    figure.suptitle("The pull between samples, against the teach (dashed: the floor the estimate claims)", fontsize=10)
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    plt.close(figure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_texture_arguments(parser)
    parser.add_argument("--models", nargs="+", choices=DEFOCUS_SHAPES, default=list(DEFAULT_MODELS),
                        help="defocus models (default: gaussian disc)")
    parser.add_argument("--phases", type=int, default=8,
                        help="where the taught view's focus falls between samples: this many evenly over a step "
                             "(default 8; 1: on a sample, where the bias vanishes by symmetry)")
    parser.add_argument("--electrons", type=float, default=ELECTRONS,
                        help=f"the dose whose noisy twin each noise-free sweep is read as (per grey level at full "
                             f"scale; default {ELECTRONS:g}, the tables'; 0: noise-free throughout)")
    parser.add_argument("--seed", type=int, default=15, help="the noisy twins' draw")
    parser.add_argument("--out", type=Path, default=RESULTS / "tilt_sampling.json",
                        help="the results (JSON; the plot beside it as .png; default %(default)s)")
    args = parser.parse_args(argv)
    if args.phases < 1:
        parser.error("--phases must be at least 1")
    if not args.electrons >= 0:
        parser.error("--electrons must be 0 (noise-free) or more")
    textures = read_textures(parser, args.images, args.image_files)
    started = time.monotonic()
    results: dict[str, dict[str, dict]] = {}
    bar = Progress("sampling", len(textures) * len(args.models) * args.phases)
    for name, texture in textures.items():
        for shape in args.models:
            results.setdefault(shape, {})[name] = one_texture(
                texture, shape, args.phases, args.electrons, args.seed, lambda note, name=name, shape=shape: bar.step(f"{name}, {shape}: {note}"))
    bar.close()
    magnitudes = [float(np.hypot(alpha, beta)) for alpha, beta, _ in POSES]
    read_as = (f"read as at {args.electrons:g} electrons per grey level" if args.electrons > 0
               else "read without noise")
    print(f"\nNoise-free sweeps ({read_as}), the taught view's focus at {args.phases} phase(s) of a step; the "
          f"largest |error| (degrees, alpha or beta) over them. {time.monotonic() - started:.0f} s.\n")
    print("| image | defocus | measure | taught view | " + " | ".join(f"{value:.1f} deg from it" for value in magnitudes)
          + " | floor claimed | refused |")
    print("| --- | --- | --- | --- | " + " | ".join("---" for _ in POSES) + " | --- | --- |")
    for shape, rows in results.items():
        for name, row in rows.items():
            for measure, reading in row.items():
                print(f"| {name} | {shape} | {'eq. 13' if measure == 'normalized_variance' else measure} | "
                      f"{reading['taught']:.3f} | " + " | ".join(f"{value:.3f}" for value in reading["against"])
                      + f" | {span(reading['floor'])} | "
                      f"{sum(reading['refused'])} of {args.phases * len(POSES)} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(jsontext.dumps({"field_px": FIELD_PX, "field_um": FIELD_UM, "depth_of_field_um": DEPTH_OF_FIELD_UM,
                                        "kernel": KERNEL, "phases": args.phases, "electrons": args.electrons,
                                        "read_noise": READ_NOISE if args.electrons > 0 else 0.0, "seed": args.seed,
                                        "poses": [list(p) for p in POSES],
                                        "sampling_bias_steps": SAMPLING_BIAS_STEPS, "results": results}, indent=1))
    plot(results, args.out.with_suffix(".png"))
    print(f"\nwrote {args.out} and {args.out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    raise SystemExit(main())
