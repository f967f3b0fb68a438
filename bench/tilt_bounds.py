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
  refused, to see how far off it would be), and how many of the draws it refuses;
* **where the reading loses**, by each measure: the share of its information in the
  kernels the estimator reads, how much more their depths scatter than each kernel's
  bound allows, and the plane through them weighed by the information itself
  (``measure_information``, ``normalized_variance_information``) beside semservo's;
  and the chain plotted per view (bench/results/tilt_bounds.png).

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
from semservo.focus_sweeps import (DEFOCUS_SHAPES, information_tilt_bound, measure_information,  # noqa: E402
                                   measure_tilt_bound, normalized_variance_information, pixel_tilt_bound)
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
    return angles_of(robust_plane(depths, KERNEL, pixel_um, uncertainties=weights))


def angles_of(plane) -> tuple[float, float]:
    """A plane's alpha, beta (degrees), as :func:`tilt_from_depths` reads its slopes."""
    _, slope_x, slope_y = plane.coefficients
    return float(np.degrees(np.arctan(slope_y))), float(np.degrees(np.arctan(-slope_x * np.cos(np.arctan(slope_y)))))


def rms(angles) -> tuple[float, float]:
    """The RMS of alpha and of beta over the draws (true 0)."""
    return tuple(float(v) for v in np.sqrt(np.nanmean(np.array(angles) ** 2, axis=0)))


def reading_losses(depth_maps, information: np.ndarray, pixel_um: float) -> dict:
    """Where a measure's reading of one view loses against the measure's bound, over
    ``depth_maps`` (``kernel_depths`` of each draw) and ``information`` (each kernel's
    Fisher information about its depth through the measure, 1 / um^2):

    * ``exact_weights``: the RMS of the robust plane's angles (true 0) through each
      draw's depths weighed by the information itself instead of the estimator's
      standard errors: the plane's own loss, apart from the weights';
    * ``information_read``: the share of the information in the kernels that plane keeps
      in at least half of the draws (what the clear-peak test leaves out, and the
      depths so far off that the plane gives them no weight, cost the rest);
    * ``kernels``: how much more those kernels' depths (where kept) scatter over the
      draws than their bounds allow, sqrt of the information-weighted mean of
      (scatter / bound)^2 (the plane weighs them so; 1: each kernel read as well as its
      curve allows)."""
    informed = information > 1e-12 * information.max()
    exact = np.where(informed, 1.0 / np.sqrt(np.where(informed, information, 1.0)), np.nan)
    angles, kept = [], []
    for each in depth_maps:
        plane = robust_plane(np.where(informed, each.depths, np.nan), KERNEL, pixel_um, uncertainties=exact)
        angles.append(angles_of(plane))
        kept.append(np.where(plane.weights > 0, each.depths, np.nan))
    kept = np.stack(kept)
    read = np.isfinite(kept).sum(axis=0) >= max(2, int(np.ceil(len(depth_maps) / 2)))
    total = float(information.sum())
    scatter = np.array([np.nanstd(column, ddof=1) for column in kept[:, read].T])
    weights = information[read]
    kernels = float(np.sqrt(np.sum(weights**2 * scatter**2) / np.sum(weights))) if read.any() else float("nan")
    return {"exact_weights": rms(angles),
            "information_read": float(weights.sum() / total) if total > 0 else float("nan"), "kernels": kernels}


def one_view(texture: np.ndarray, shape: str, draws: int, seed: int, step) -> dict:
    view = lab(texture, shape, seed)
    distances = plan_sweep(0.0, DEPTH_OF_FIELD_UM, FIELD_UM)
    scene = view._scene_at(FLAT)
    rng = np.random.default_rng(seed)
    row = {"pixels": pixel_tilt_bound(scene, distances, ELECTRONS, READ_NOISE)}
    step("pixels")
    information = {"gradient": measure_information(scene, distances, gradient, KERNEL, ELECTRONS, READ_NOISE,
                                                   rng=rng)}
    row["gradient"] = information_tilt_bound(scene, information["gradient"], KERNEL)
    step("gradient")
    information["normalized_variance"] = normalized_variance_information(scene, distances, KERNEL, ELECTRONS,
                                                                         READ_NOISE)
    row["eq13"] = information_tilt_bound(scene, information["normalized_variance"], KERNEL)
    row["eq13_monte_carlo"] = measure_tilt_bound(scene, distances, normalized_variance, KERNEL, ELECTRONS, READ_NOISE,
                                                 rng=rng)
    step("eq. 13")
    sweep_step = float(distances[1] - distances[0])
    readings = {measure: {"angles": [], "claimed": [], "refused": 0, "depths": []} for measure in FOCUS_MEASURES}
    for _ in range(draws):
        sweep = view.sweep(FLAT, distances)
        for measure, reading in readings.items():  # both measures on the same sweeps
            depths = kernel_depths(sweep, distances, KERNEL, view.pixel_um, measure=measure)
            estimate = tilt_from_depths(depths.depths, KERNEL, view.pixel_um, sweep_step, depths.uncertainties)
            reading["refused"] += int(estimate.confidence <= 0)
            reading["claimed"].append((estimate.alpha_uncertainty_deg, estimate.beta_uncertainty_deg))
            reading["angles"].append(plane_angles(depths.depths, depths.uncertainties, view.pixel_um))
            reading["depths"].append(depths)
        step("semservo")
    row["semservo"] = {measure: {"claimed": tuple(float(v) for v in np.nanmedian(np.array(reading["claimed"]), axis=0)),
                                 "rms": rms(reading["angles"]), "refused": reading["refused"],
                                 **reading_losses(reading["depths"], information[measure], view.pixel_um)}
                       for measure, reading in readings.items()}
    row["draws"] = draws
    return row


def plot(results: dict[str, dict[str, dict]], path: Path) -> None:
    """The chain of losses per view: a panel per defocus model, and for each image and
    measure the pixels' bound, the measure's bound, semservo's RMS and its claim (the
    worse of alpha and beta), beside the line a teach may keep and where pooling the
    teach's sweeps at 1 / sqrt(n) could bring a sweep down to it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shapes = list(results)
    names = list(next(iter(results.values())))
    figure, axes = plt.subplots(1, len(shapes), figsize=(1.3 * len(names) * len(shapes) + 1, 4.2), squeeze=False,
                                sharey=True)
    measures = {"normalized_variance": ("eq. 13", "C0", -0.15), "gradient": ("gradient", "C1", 0.15)}
    for axis, shape in zip(axes[0], shapes):
        for index, name in enumerate(names):
            row = results[shape][name]
            axis.plot(index, max(row["pixels"]), "k_", markersize=14, label="pixels' bound" if index == 0 else None)
            for measure, (label, colour, offset) in measures.items():
                bound = max(row["eq13" if measure == "normalized_variance" else "gradient"])
                reading = row["semservo"][measure]
                x = index + offset
                axis.plot([index, x, x], [max(row["pixels"]), bound, max(reading["rms"])], "-", color=colour,
                          linewidth=0.8)
                axis.plot(x, bound, "s", color=colour, markersize=4, label=f"{label}: bound" if index == 0 else None)
                axis.plot(x, max(reading["rms"]), "o", color=colour, markersize=5,
                          label=f"{label}: semservo's RMS" if index == 0 else None)
                axis.plot(x, max(reading["claimed"]), "x", color=colour, markersize=5,
                          label=f"{label}: its claim" if index == 0 else None)
        axis.axhline(MAX_TAUGHT_UNCERTAINTY_DEG, color="k", linewidth=0.8)
        axis.axhline(2 * MAX_TAUGHT_UNCERTAINTY_DEG, color="k", linewidth=0.8, linestyle=":")
        axis.set_yscale("log")
        axis.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=7)
        axis.set_title(f"{shape} defocus", fontsize=9)
        axis.grid(True, which="both", axis="y", alpha=0.3)
    axes[0, 0].set_ylabel("one sweep's standard error, worse tilt (degrees)")
    axes[0, 0].legend(fontsize=6, loc="upper left")
    figure.suptitle(f"Where the tilts' limit lies (solid: a teach may keep ±{MAX_TAUGHT_UNCERTAINTY_DEG:.3f}°; "
                    "dotted: 4 sweeps at 1/sqrt(n) reach it from there)", fontsize=9)
    figure.tight_layout()
    figure.savefig(path, dpi=90)
    plt.close(figure)


def pair(values) -> str:
    return f"{values[0]:.3f}, {values[1]:.3f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_texture_arguments(parser)
    parser.add_argument("--models", nargs="+", choices=DEFOCUS_SHAPES, default=list(DEFAULT_MODELS),
                        help="defocus models (default: gaussian disc)")
    parser.add_argument("--draws", type=int, default=16,
                        help="one-sweep estimates of the flat view per image and model (default 16, at least 2)")
    parser.add_argument("--seed", type=int, default=15, help="the noise's draw (default 15)")
    parser.add_argument("--out", type=Path, default=RESULTS / "tilt_bounds.json",
                        help="the results (JSON; the plot beside it as .png; default %(default)s)")
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
    print("\nWhere each measure's reading loses against its bound (the same sweeps): the share of the measure's "
          "information in the kernels read (a depth the plane keeps in at least half of the draws); how much more "
          "those kernels' "
          "depths scatter than their bounds allow (information-weighted); the RMS of the robust plane (alpha, beta, "
          "degrees, true 0) weighed by the information itself, and by semservo's own standard errors.\n")
    print("| image | defocus | measure | bound | information in the kernels read | kernels' depths: scatter / bound "
          "| plane, exact weights: RMS | semservo: RMS |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for shape, rows in results.items():
        for name, row in rows.items():
            for measure, bound in (("normalized_variance", row["eq13"]), ("gradient", row["gradient"])):
                reading = row["semservo"][measure]
                print(f"| {name} | {shape} | {'eq. 13' if measure == 'normalized_variance' else measure} "
                      f"| {pair(bound)} | {reading['information_read']:.1%} | {reading['kernels']:.2f} "
                      f"| {pair(reading['exact_weights'])} | {pair(reading['rms'])} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(jsontext.dumps({"field_px": FIELD_PX, "field_um": FIELD_UM, "depth_of_field_um": DEPTH_OF_FIELD_UM,
                                        "electrons": ELECTRONS, "read_noise": READ_NOISE, "kernel": KERNEL,
                                        "draws": args.draws, "seed": args.seed, "results": results}, indent=1))
    plot(results, args.out.with_suffix(".png"))
    print(f"\nwrote {args.out} and {args.out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    raise SystemExit(main())
