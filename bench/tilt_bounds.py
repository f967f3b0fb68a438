"""Where the tilts from focus are limited on real textures: the measure, the reading or
the picture (issue #27's refusals).

For the taught (flat) view of each real SEM image of ``../shared/data/sem-images``, under
each defocus model, the same sweeps as ``bench/tilt_real.py`` (``semservo.focus_sweeps``:
512 px over 25 um, 21 working distances planned for a depth of field of 2.5 um, 1000
electrons per grey level at full scale), this prints the standard errors of alpha and
beta from one sweep, degrees:

* **pixels**: the Cramer-Rao bound from the sweep's pixels themselves
  (``pixel_tilt_bound``): what no estimator can beat, whatever it measures, even one that
  knew the sharp texture and the blur;
* **gradient**: the bound of the estimator's other focus measure, each kernel's gradient
  energy (Sobel on the frame smoothed by 1 px, over the kernel's mean; ``gradient_energy``,
  ``SEMSERVO_ESTIMATOR__TILT_FOCUS_MEASURE=gradient``), by ``measure_tilt_bound`` (Monte Carlo);
* **eq. 13**: the bound of the paper's measure, the estimator's (``tilt_bound``;
  analytic), and its Monte Carlo check;
* **semservo, one sweep**, by each focus measure on the same sweeps: what the estimator
  claims (the median of its standard errors) and what it does (the RMS of its plane's
  angles over ``--draws`` sweeps, true 0; the plane is read even where the estimate is
  refused, to see how far off it would be), and how many of the draws it refuses.

A refusal is the picture's where even the pixels' bound is near the line a teach may keep
(``MAX_TAUGHT_UNCERTAINTY_DEG``); the measure's where eq. 13's bound is far above the
pixels'; the reading's where semservo's RMS is far above eq. 13's bound.

    ./dev bench tilt_bounds                       # all six images, both models
    ./dev bench tilt_bounds --images drift_pair_after --draws 4
    ./dev bench tilt_bounds --image-files ~/pictures/wafer.tif     # can focus pin the tilts on your sample?
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
                       add_texture_arguments, lab, read_textures)

from semservo import jsontext  # noqa: E402
from semservo.estimation.tilt import (FOCUS_MEASURES, MAX_TAUGHT_UNCERTAINTY_DEG, focus_curves,  # noqa: E402
                                      gradient_energy, kernel_depths, plan_sweep, robust_plane, tilt_from_depths,
                                      with_excess_scatter)
from semservo.focus_sweeps import DEFOCUS_SHAPES, measure_tilt_bound, pixel_tilt_bound, tilt_bound  # noqa: E402
from semservo.reproduce import Progress  # noqa: E402

RESULTS = Path(__file__).parent / "results"
KERNEL = 32
FLAT = (0.0, 0.0, 0.0)


def normalized_variance(frame: np.ndarray) -> np.ndarray:
    """eq. 13 per kernel, as the estimator reads it (``focus_curves``)."""
    return focus_curves(frame[np.newaxis], KERNEL)[0]


def gradient(frame: np.ndarray) -> np.ndarray:
    """The estimator's gradient measure per kernel (``gradient_energy``)."""
    return gradient_energy(frame, KERNEL)


def plane_angles(depths, uncertainties, pixel_um: float) -> tuple[float, float]:
    """The robust plane's alpha, beta (degrees) through the kernel depths, refused or not
    (as :func:`tilt_from_depths` fits it)."""
    weights = with_excess_scatter(depths, uncertainties, KERNEL, pixel_um)
    _, slope_x, slope_y = robust_plane(depths, KERNEL, pixel_um, uncertainties=weights).coefficients
    return float(np.degrees(np.arctan(slope_y))), float(np.degrees(np.arctan(-slope_x * np.cos(np.arctan(slope_y)))))


def one_view(texture: np.ndarray, shape: str, draws: int, seed: int, step) -> dict:
    view = lab(texture, shape, seed)
    distances = plan_sweep(0.0, DEPTH_OF_FIELD_UM, FIELD_UM)
    scene = view._scene_at(FLAT)
    rng = np.random.default_rng(seed)
    row = {"pixels": pixel_tilt_bound(scene, distances, ELECTRONS, READ_NOISE)}
    step("pixels")
    row["gradient"] = measure_tilt_bound(scene, distances, gradient, KERNEL, ELECTRONS, READ_NOISE, rng=rng)
    step("gradient")
    row["eq13"] = tilt_bound(scene, distances, KERNEL, ELECTRONS, READ_NOISE)
    row["eq13_monte_carlo"] = measure_tilt_bound(scene, distances, normalized_variance, KERNEL, ELECTRONS, READ_NOISE,
                                                 rng=rng)
    step("eq. 13")
    sweep_step = float(distances[1] - distances[0])
    readings = {measure: {"angles": [], "claimed": [], "refused": 0} for measure in FOCUS_MEASURES}
    for _ in range(draws):
        sweep = view.sweep(FLAT, distances)
        for measure, reading in readings.items():  # both measures on the same sweeps
            depths = kernel_depths(sweep, distances, KERNEL, view.pixel_um, measure=measure)
            estimate = tilt_from_depths(depths.depths, KERNEL, view.pixel_um, sweep_step, depths.uncertainties)
            reading["refused"] += int(estimate.confidence <= 0)
            reading["claimed"].append((estimate.alpha_uncertainty_deg, estimate.beta_uncertainty_deg))
            reading["angles"].append(plane_angles(depths.depths, depths.uncertainties, view.pixel_um))
        step("semservo")
    row["semservo"] = {measure: {"claimed": tuple(float(v) for v in np.nanmedian(np.array(reading["claimed"]), axis=0)),
                                 "rms": tuple(float(v) for v in np.sqrt(np.nanmean(np.array(reading["angles"]) ** 2,
                                                                                   axis=0))),
                                 "refused": reading["refused"]}
                       for measure, reading in readings.items()}
    row["draws"] = draws
    return row


def pair(values) -> str:
    return f"{values[0]:.3f}, {values[1]:.3f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_texture_arguments(parser)
    parser.add_argument("--models", nargs="+", choices=DEFOCUS_SHAPES, default=list(DEFAULT_MODELS),
                        help="defocus models (default: gaussian disc)")
    parser.add_argument("--draws", type=int, default=8,
                        help="one-sweep estimates of the flat view per image and model (default 8, at least 2)")
    parser.add_argument("--seed", type=int, default=15, help="the noise's draw (default 15)")
    parser.add_argument("--out", type=Path, default=RESULTS / "tilt_bounds.json",
                        help="the results (JSON; default %(default)s)")
    args = parser.parse_args(argv)
    if args.draws < 2:
        parser.error("--draws must be at least 2 (an RMS of one draw says little)")
    textures = read_textures(parser, args.images, args.image_files)
    started = time.monotonic()
    results: dict[str, dict[str, dict]] = {}
    bar = Progress("bounds", len(textures) * len(args.models) * (3 + args.draws))
    for name, texture in textures.items():
        for shape in args.models:
            results.setdefault(shape, {})[name] = one_view(texture, shape, args.draws, args.seed,
                                                           lambda note, name=name, shape=shape: bar.step(
                                                               f"{name}, {shape}: {note}"))
    bar.close()
    print(f"\nOne sweep of the flat view ({FIELD_PX} px over {FIELD_UM:g} um, depth of field {DEPTH_OF_FIELD_UM:g} "
          f"um, {ELECTRONS:g} electrons per grey level, read noise {READ_NOISE:g}): standard errors of alpha, beta "
          f"(degrees); a teach may keep +-{MAX_TAUGHT_UNCERTAINTY_DEG:.3f}. {time.monotonic() - started:.0f} s.\n")
    print("| image | defocus | pixels (no estimator beats) | gradient measure | eq. 13 (Monte Carlo) "
          "| semservo, eq. 13: claims; RMS; refused | semservo, gradient: claims; RMS; refused |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for shape, rows in results.items():
        for name, row in rows.items():
            read = [f"{pair(reading['claimed'])}; {pair(reading['rms'])}; {reading['refused']} of {row['draws']}"
                    for reading in (row["semservo"][measure] for measure in FOCUS_MEASURES)]
            print(f"| {name} | {shape} | {pair(row['pixels'])} | {pair(row['gradient'])} | {pair(row['eq13'])} "
                  f"({pair(row['eq13_monte_carlo'])}) | {' | '.join(read)} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(jsontext.dumps({"field_px": FIELD_PX, "field_um": FIELD_UM, "depth_of_field_um": DEPTH_OF_FIELD_UM,
                                        "electrons": ELECTRONS, "read_noise": READ_NOISE, "kernel": KERNEL,
                                        "draws": args.draws, "seed": args.seed, "results": results}, indent=1))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    raise SystemExit(main())
