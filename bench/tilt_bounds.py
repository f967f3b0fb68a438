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
  ``SEMSERVO_ESTIMATOR__TILT_FOCUS_MEASURE=gradient``), by Monte Carlo
  (``measure_information``, ``information_tilt_bound``);
* **eq. 13**: the bound of the paper's measure, the estimator's (``tilt_bound``;
  analytic), and its Monte Carlo check;
* **semservo, one sweep**, by each focus measure on the same sweeps: what the estimator
  claims (the median of its standard errors) and what it does (the RMS of its plane's
  angles over ``--draws`` sweeps, true 0; the plane is read even where the estimate is
  refused, to see how far off it would be), and how many of the draws it refuses;
* **where the reading loses**, by each measure against its Monte Carlo bound: the share
  of its information in the kernels semservo's plane keeps, how much more their depths
  scatter than each kernel's bound allows (and how far they are from the truth), and the
  plane through them weighed by the information itself beside semservo's (with the mean
  of semservo's angles: a bias the draws share); and the chain plotted per view
  (bench/results/tilt_bounds.png).

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
                                   pixel_tilt_bound, tilt_bound)
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


#: Each focus measure's name in the tables, and the bound its reading is weighed against
#: in the losses (both by Monte Carlo, on the same footing).
MEASURES = {"normalized_variance": ("eq. 13", "eq13_monte_carlo"), "gradient": ("gradient", "gradient")}


def estimator_plane(depths, uncertainties, pixel_um: float):
    """The robust plane through the kernel depths, refused or not, as
    :func:`tilt_from_depths` fits it (``PlaneFit``: its ``weights`` 0 where a kernel is
    left out)."""
    weights = with_excess_scatter(depths, uncertainties, KERNEL, pixel_um)
    return robust_plane(depths, KERNEL, pixel_um, uncertainties=weights)


def angles_of(plane) -> tuple[float, float]:
    """A plane's alpha, beta (degrees, ``PlaneFit.tilts_deg``); NaN where fewer than 3
    kernels hold it."""
    if np.count_nonzero(plane.weights > 0) < 3:
        return float("nan"), float("nan")
    return plane.tilts_deg


def mean_over_draws(values) -> tuple[float, ...]:
    """Each column's mean over the draws that have it (NaN, quietly, where none has:
    a texture whose every draw is refused)."""
    values = np.array(values, dtype=np.float64)
    seen = np.isfinite(values)
    return tuple(float(np.sum(column[kept]) / np.sum(kept)) if kept.any() else float("nan")
                 for column, kept in zip(values.T, seen.T))


def rms(angles) -> tuple[float, float]:
    """The RMS of alpha and of beta over the draws (true 0)."""
    return tuple(float(np.sqrt(v)) for v in mean_over_draws(np.square(angles)))


def reading_losses(depth_maps, kept, information: np.ndarray, pixel_um: float) -> dict:
    """Where a measure's reading of one view loses against the measure's bound, over
    ``depth_maps`` (``kernel_depths`` of each draw; the flat view, so every kernel's true
    depth is 0), ``kept`` (each draw's kernels that semservo's plane weighs) and
    ``information`` (each kernel's Fisher information about its depth through the
    measure, 1 / um^2):

    * ``information_read``: the share of the information in the kernels semservo's plane
      keeps in at least half of the draws (what the clear-peak test leaves out, and
      depths so far off that the plane gives them no weight, cost the rest);
    * ``scatter_over_bound``: how much more those kernels' depths (where kept) scatter
      over the draws than their bounds allow, sqrt of the information-weighted mean of
      (scatter / bound)^2 (the plane weighs them so; 1: each kernel read as well as its
      curve allows); ``error_over_bound`` the same about the true depth, so with each
      kernel's own bias (the pull between samples);
    * ``rms_exact_weights``: the RMS of the robust plane's angles (true 0) through each
      draw's depths weighed by the information itself instead of semservo's standard
      errors: the plane's loss, apart from the weights'."""
    informed = information > 1e-12 * information.max()
    exact = np.where(informed, 1.0 / np.sqrt(np.where(informed, information, 1.0)), np.nan)
    angles = [angles_of(robust_plane(np.where(informed, each.depths, np.nan), KERNEL, pixel_um, uncertainties=exact))
              for each in depth_maps]
    depths = np.stack([np.where(weighed, each.depths, np.nan) for each, weighed in zip(depth_maps, kept)])
    read = np.isfinite(depths).sum(axis=0) >= max(2, int(np.ceil(len(depth_maps) / 2)))
    total = float(information.sum())
    weights = information[read]

    def over_bound(spread: np.ndarray) -> float:
        return float(np.sqrt(np.sum(weights**2 * spread**2) / np.sum(weights))) if read.any() else float("nan")

    return {"information_read": float(weights.sum() / total) if total > 0 else float("nan"),
            "scatter_over_bound": over_bound(np.nanstd(depths[:, read], axis=0, ddof=1)),
            "error_over_bound": over_bound(np.sqrt(np.nanmean(depths[:, read] ** 2, axis=0))),
            "rms_exact_weights": rms(angles)}


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
    row["eq13"] = tilt_bound(scene, distances, KERNEL, ELECTRONS, READ_NOISE)
    information["normalized_variance"] = measure_information(scene, distances, normalized_variance, KERNEL, ELECTRONS,
                                                             READ_NOISE, rng=rng)
    row["eq13_monte_carlo"] = information_tilt_bound(scene, information["normalized_variance"], KERNEL)
    step("eq. 13")
    sweep_step = float(distances[1] - distances[0])
    readings = {measure: {"angles": [], "claimed": [], "refused": 0, "depths": [], "kept": []}
                for measure in FOCUS_MEASURES}
    for _ in range(draws):
        sweep = view.sweep(FLAT, distances)
        for measure, reading in readings.items():  # both measures on the same sweeps
            depths = kernel_depths(sweep, distances, KERNEL, view.pixel_um, measure=measure)
            estimate = tilt_from_depths(depths.depths, KERNEL, view.pixel_um, sweep_step, depths.uncertainties)
            reading["refused"] += int(estimate.confidence <= 0)
            reading["claimed"].append((estimate.alpha_uncertainty_deg, estimate.beta_uncertainty_deg))
            plane = estimator_plane(depths.depths, depths.uncertainties, view.pixel_um)
            reading["angles"].append(angles_of(plane))
            reading["depths"].append(depths)
            reading["kept"].append(plane.weights > 0)
        step("semservo")
    row["semservo"] = {measure: {"claimed": tuple(float(v) for v in np.nanmedian(np.array(reading["claimed"]), axis=0)),
                                 "rms": rms(reading["angles"]),
                                 "mean": mean_over_draws(reading["angles"]),
                                 "refused": reading["refused"],
                                 **reading_losses(reading["depths"], reading["kept"], information[measure],
                                                  view.pixel_um)}
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
    width = max(1.3 * len(names), 4.0)
    figure, axes = plt.subplots(1, len(shapes), figsize=(width * len(shapes) + 0.8, 4.4), squeeze=False, sharey=True)
    colours = {"normalized_variance": ("C0", -0.15), "gradient": ("C1", 0.15)}
    for axis, shape in zip(axes[0], shapes):
        for index, name in enumerate(names):
            row = results[shape][name]
            first = index == 0 and axis is axes[0, 0]  # label each kind of mark once
            axis.plot(index, max(row["pixels"]), "k_", markersize=14, label="pixels' bound" if first else None)
            for measure, (colour, offset) in colours.items():
                label, bound_key = MEASURES[measure]
                bound, reading, x = max(row[bound_key]), row["semservo"][measure], index + offset
                axis.plot([index, x, x], [max(row["pixels"]), bound, max(reading["rms"])], "-", color=colour,
                          linewidth=0.8)
                axis.plot(x, bound, "s", color=colour, markersize=4, label=f"{label}: bound" if first else None)
                axis.plot(x, max(reading["rms"]), "o", color=colour, markersize=5,
                          label=f"{label}: semservo's RMS" if first else None)
                axis.plot(x, max(reading["claimed"]), "x", color=colour, markersize=5,
                          label=f"{label}: its claim" if first else None)
        first = axis is axes[0, 0]
        axis.axhline(MAX_TAUGHT_UNCERTAINTY_DEG, color="k", linewidth=0.8,
                     label=f"a teach may keep ±{MAX_TAUGHT_UNCERTAINTY_DEG:.3f}°" if first else None)
        axis.axhline(2 * MAX_TAUGHT_UNCERTAINTY_DEG, color="k", linewidth=0.8, linestyle=":",
                     label="4 sweeps at 1/√n reach it from here" if first else None)
        axis.set_yscale("log")
        axis.set_xticks(range(len(names)), names, rotation=30, ha="right", fontsize=7)
        axis.set_xlim(-0.6, len(names) - 0.4)
        axis.set_title(f"{shape} defocus", fontsize=9)
        axis.grid(True, which="both", axis="y", alpha=0.3)
    axes[0, 0].set_ylabel("one sweep's standard error, worse tilt (degrees)")
    figure.suptitle("Where the tilts' limit lies: one sweep of the flat view", fontsize=9)
    figure.tight_layout()
    # Beside the panels, not over them (saved with the figure grown to hold it).
    figure.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
    figure.savefig(path, dpi=90, bbox_inches="tight")
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
    print("\nWhere each measure's reading loses against its bound (the same sweeps; both bounds by Monte Carlo): "
          "the share of the measure's information in the kernels semservo's plane keeps in at least half of the "
          "draws; how much more those kernels' depths scatter than their bounds allow, and (in brackets) how far "
          "they are from the true depth, information-weighted; the RMS of the robust plane (alpha, beta, degrees, "
          "true 0) weighed by the information itself, and by semservo's own standard errors, with its mean.\n")
    print("| image | defocus | measure | bound | information in the kernels read | kernels' depths: scatter "
          "(error) / bound | plane, exact weights: RMS | semservo: RMS (mean) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for shape, rows in results.items():
        for name, row in rows.items():
            for measure, (label, bound_key) in MEASURES.items():
                reading = row["semservo"][measure]
                print(f"| {name} | {shape} | {label} | {pair(row[bound_key])} | {reading['information_read']:.1%} "
                      f"| {reading['scatter_over_bound']:.2f} ({reading['error_over_bound']:.2f}) "
                      f"| {pair(reading['rms_exact_weights'])} | {pair(reading['rms'])} "
                      f"({reading['mean'][0]:+.3f}, {reading['mean'][1]:+.3f}) |")
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
