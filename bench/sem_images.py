"""Motion estimation on real SEM images of other instruments, every method side by side.

Per image of other instruments and samples, every method on the same pairs, side by side
in one run.

The estimator's constants were chosen on the 2013 recording; its fixes for other scenes
were developed on three of the images of ``../shared/data/sem-images`` (``developed
on``); two were never looked at while choosing anything (``held out``). Images are read
through ``semservo.imagefiles``, data bars cropped. For each image:

  translation   pairs with exactly known shifts in thirds, quarters and fifths of a pixel
                (block factors 3, 4, 5; ``semservo.pairs``), at three doses (low,
                moderate, high Poisson-Gaussian noise) and with a brightness/contrast
                change. Every method
                gets its own copy of each image (OpenCV 5's phaseCorrelate writes into
                its inputs at some sizes).
  confidence    semservo's confidence against the controller's ``min_confidence``:
                estimates off by more than 0.5 px that it would act on (target: none),
                and good ones (within 0.5 px) it would refuse.
  rotation      a centred square turned by known angles (-170 to +120 degrees, near
                +-90 and small turns included) under moderate noise: semservo against
                imreg_dft.
  turn under    the same square turned by -20 to +20 degrees and its view moved by up to
  a shift       a quarter of the field (semservo.pairs.turned_and_moved: the content
                that enters comes from the rest of the image, mirrored beyond it): the
                first estimate of a run that starts far from the goal; the turn's error
                and the shift's of the estimates semservo accepts.
  hard frames   the translation pairs as a noisy, low-contrast frame (contrast cut to
                0.3 and 0.2 about the mean, 200 and 100 electrons per grey level): every
                method, and semservo's refusals.
  stress        the confidence where estimates do go wrong: the same pairs at a dose far
                below any usable one, and a disc and a ring (no angle to tell) turned.
  consistency   the real drifted pair (A->B against -(B->A)) and the 2013 run (chains
                ref->a + a->b - ref->b): no truth needed, the numbers must agree.
  speed         time per 512 x 512 frame of the 2013 run, one core, against
                cv2.phaseCorrelate in the same run (bench/estimator.py's timing, in a
                clean process).

Prints one table per case (markdown), writes bench/results/sem_images.json.

    ./dev bench sem_images            # or: python bench/sem_images.py --pairs 4
"""

from __future__ import annotations

import os

# One core for every method, before numpy and OpenCV load their thread pools.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
import estimator as peers  # noqa: E402  (the methods of bench/estimator.py, the same code)

from semservo import jsontext  # noqa: E402
from semservo.config import find_recorded_run, find_sem_images  # noqa: E402
from semservo.estimation import MotionEstimator, rotate_about_centre  # noqa: E402
from semservo.imagefiles import read_sem_image  # noqa: E402
from semservo.pairs import centred_window, poisson_gaussian, shifted_pair, turned_and_moved  # noqa: E402
from services.controller.core import RunSettings  # noqa: E402

#: What the estimator was developed on (its constants chosen on the 2013 frames; the
#: single-FFT full-resolution fit judged on these too, and the rotation's refinement on
#: the image itself designed on the drift and hole images, where the log-polar estimate
#: wandered), and what no choice ever looked at.
TUNED_ON = ("2013 reference", "fibsem_slice_cells", "hole_low_mag", "drift_pair_before")
HELD_OUT = ("jeol_grid", "tescan_aperture")
IMAGES = ("jeol_grid", "tescan_aperture", "fibsem_slice_cells", "hole_low_mag", "drift_pair_before")
CONDITIONS = {  # electrons per full-scale grey level, read noise; contrast gain, offset
    "low noise": (5000, 1.0, 1.0, 0.0),
    "moderate noise": (1000, 2.0, 1.0, 0.0),
    "high noise": (200, 4.0, 1.0, 0.0),
    "brightness/contrast": (1000, 2.0, 1.6, 30.0),
}
FACTORS = (3, 4, 5)
MAX_SHIFT_PX = 6  # at the pair's resolution
PAIR_SIDE = 256  # pixels, at the pair's resolution (less where the image is smaller)
BAD_PX = 0.5
FAILURE_PX = 1.0
ANGLES = (-170.0, -89.0, -60.0, -25.0, -7.5, -1.2, -0.3, 0.4, 2.0, 12.0, 33.0, 60.0, 89.5, 120.0)
FAILURE_DEG = 1.0


def grey(pixels: np.ndarray) -> np.ndarray:
    """0..255 floats whatever the bit depth (the noise model is per 8-bit grey level)."""
    pixels = pixels.astype(np.float64)
    return pixels / 257.0 if pixels.max() > 255 else pixels


def load_images() -> dict[str, np.ndarray]:
    images = {"2013 reference": grey(read_sem_image(find_recorded_run() / "reference.png").pixels)}
    for name in IMAGES:
        images[name] = grey(read_sem_image(find_sem_images() / f"{name}.tif").pixels)
    return images


def pairs_for(image: np.ndarray, count: int, rng) -> list:
    """``count`` pairs per block factor, shifts up to MAX_SHIFT_PX, from a central window."""
    pairs = []
    for factor in FACTORS:
        margin = MAX_SHIFT_PX * factor
        side = min(PAIR_SIDE * factor + 2 * margin, min(image.shape) // factor * factor)
        top, left = (image.shape[0] - side) // 2, (image.shape[1] - side) // 2
        window = image[top:top + side, left:left + side]
        for _ in range(count):
            dx, dy = rng.integers(-MAX_SHIFT_PX * factor, MAX_SHIFT_PX * factor + 1, size=2) / factor
            pairs.append(shifted_pair(window, float(dx), float(dy), factor, margin=margin))
    return pairs


def noisy(pair, condition: str, rng) -> tuple[np.ndarray, np.ndarray]:
    electrons, read, gain, offset = CONDITIONS[condition]
    reference = poisson_gaussian(pair.reference, electrons, read, rng)
    current = poisson_gaussian(pair.current, electrons, read, rng) * gain + offset
    return reference, current


def run_translation(images: dict, count: int, rng, min_confidence: float, progress) -> dict:
    results = {}
    for name, image in images.items():
        pairs = pairs_for(image, count, rng)
        inputs = [(pair, *noisy(pair, condition, rng)) for condition in CONDITIONS for pair in pairs]
        errors: dict[str, list[float]] = {method: [] for method in peers.TRANSLATION_METHODS}
        acted_on_bad, refused_good, good = 0, 0, 0
        for pair, reference, current in inputs:
            for method, function in peers.TRANSLATION_METHODS.items():
                dx, dy = function(reference.copy(), current.copy())  # each its own copies
                errors[method].append(float(np.hypot(dx - pair.dx, dy - pair.dy)))
            motion = MotionEstimator(reference.copy(), rotation=False).estimate(current.copy())
            error = float(np.hypot(motion.dx - pair.dx, motion.dy - pair.dy))
            if error > BAD_PX and motion.confidence >= min_confidence:
                acted_on_bad += 1
            if error <= BAD_PX:
                good += 1
                refused_good += motion.confidence < min_confidence
        results[name] = {
            "pairs": len(inputs), "side_px": [int(s) for s in pairs[-1].reference.shape],
            "methods": {method: peers.summarize(values, FAILURE_PX) for method, values in errors.items()},
            "confidence": {"bad_acted_on": acted_on_bad, "good_refused": int(refused_good), "good": good},
        }
        progress(f"translation, {name}: {len(inputs)} pairs")
    return results


#: What a new user meets on a poor day: a real image at a fraction of its contrast (about
#: its mean grey) and a low dose. (contrast kept, electrons per full-scale grey level, read noise)
HARD_CONDITIONS = {
    "low contrast (x0.3), 200 e": (0.3, 200, 2.0),
    "low contrast (x0.2), 100 e": (0.2, 100, 2.0),
}


def run_translation_stress(images: dict, count: int, rng, min_confidence: float, progress) -> dict:
    """The known-shift pairs as a noisy, low-contrast frame: each image's contrast cut to
    a fraction about its mean, then Poisson-Gaussian noise at a low dose. Every method on
    the same pairs; for semservo also the failures (> 1 px) it would act on
    (confidence at least ``min_confidence``) and the estimates it refuses."""
    results = {}
    for name, image in images.items():
        pairs = pairs_for(image, count, rng)
        results[name] = {}
        for condition, (contrast, electrons, read) in HARD_CONDITIONS.items():
            errors: dict[str, list[float]] = {method: [] for method in peers.TRANSLATION_METHODS}
            acted_on_failures = refused = 0
            for pair in pairs:
                faint = [pair.reference.mean() + contrast * (frame - pair.reference.mean())
                         for frame in (pair.reference, pair.current)]
                reference, current = (poisson_gaussian(frame, electrons, read, rng) for frame in faint)
                for method, function in peers.TRANSLATION_METHODS.items():
                    dx, dy = function(reference.copy(), current.copy())
                    errors[method].append(float(np.hypot(dx - pair.dx, dy - pair.dy)))
                motion = MotionEstimator(reference.copy(), rotation=False).estimate(current.copy())
                if motion.confidence < min_confidence:
                    refused += 1
                elif np.hypot(motion.dx - pair.dx, motion.dy - pair.dy) > FAILURE_PX:
                    acted_on_failures += 1
            results[name][condition] = {
                "pairs": len(pairs), "methods": {method: peers.summarize(values, FAILURE_PX)
                                                 for method, values in errors.items()},
                "semservo": {"failures_acted_on": acted_on_failures, "refused": refused}}
        progress(f"translation on a noisy, low-contrast frame, {name}")
    return results


#: Far below any usable dose: where estimates go wrong, so the confidence can be judged.
STRESS = (25, 8.0)  # electrons per full-scale grey level, read noise


def run_confidence_stress(images: dict, count: int, rng, min_confidence: float, progress) -> dict:
    """semservo's confidence where estimates do go wrong: the known-shift pairs at a dose
    far below any usable one, and two scenes whose angle cannot be told (a disc, a ring)
    turned by known angles. Counts estimates off by more than BAD_PX (or 1 degree) that
    it would act on (target: none), and good ones it would refuse."""
    results = {}
    electrons, read = STRESS
    for name, image in images.items():
        acted_on_bad = refused_good = good = bad = 0
        for pair in pairs_for(image, count, rng):
            reference = poisson_gaussian(pair.reference, electrons, read, rng)
            current = poisson_gaussian(pair.current, electrons, read, rng)
            motion = MotionEstimator(reference, rotation=False).estimate(current)
            error = float(np.hypot(motion.dx - pair.dx, motion.dy - pair.dy))
            trusted = motion.confidence >= min_confidence
            bad += error > BAD_PX
            acted_on_bad += error > BAD_PX and trusted
            good += error <= BAD_PX
            refused_good += error <= BAD_PX and not trusted
        results[name] = {"estimates": 3 * count, "bad": int(bad), "bad_acted_on": int(acted_on_bad),
                         "good": int(good), "good_refused": int(refused_good)}
        progress(f"confidence at a very low dose, {name}")
    rows, cols = np.mgrid[:384, :384]
    radius = np.hypot(cols - 191.5, rows - 191.5)
    scenes = {"disc": np.where(radius < 110, 180.0, 40.0), "ring": 40.0 + 140.0 * ((radius > 60) & (radius < 120))}
    electrons, read, _, _ = CONDITIONS["moderate noise"]
    for name, scene in scenes.items():
        estimator = MotionEstimator(poisson_gaussian(scene, electrons, read, rng))
        acted_on_bad = bad = 0
        for angle in ANGLES:
            turned = rotate_about_centre(scene.astype(np.float32), angle)
            motion = estimator.estimate(poisson_gaussian(turned, electrons, read, rng))
            wrong = abs((motion.rotation_deg - angle + 180) % 360 - 180) > FAILURE_DEG
            bad += wrong
            acted_on_bad += wrong and motion.confidence >= min_confidence
        results[f"{name} (turned)"] = {"estimates": len(ANGLES), "bad": int(bad), "bad_acted_on": int(acted_on_bad),
                                       "good": len(ANGLES) - int(bad), "good_refused": None}
    progress("confidence on scenes whose angle cannot be told")
    return results


def run_rotation(images: dict, rng, progress) -> dict:
    import imreg_dft

    results = {}
    electrons, read, _, _ = CONDITIONS["moderate noise"]
    for name, image in images.items():
        side = min(384, min(image.shape) // 2 * 2)
        top, left = (image.shape[0] - side) // 2, (image.shape[1] - side) // 2
        square = image[top:top + side, left:left + side].astype(np.float32)
        reference = poisson_gaussian(square, electrons, read, rng)
        ours = MotionEstimator(reference.copy())
        errors: dict[str, list[float]] = {"semservo": [], "imreg_dft.similarity": []}
        confidences = []
        for angle in ANGLES:
            current = poisson_gaussian(rotate_about_centre(square, angle), electrons, read, rng)
            motion = ours.estimate(current.copy())
            errors["semservo"].append(abs(motion.rotation_deg - angle))
            confidences.append(motion.confidence)
            peer = imreg_dft.similarity(reference.copy(), current.copy(), numiter=1, constraints={"scale": [1, 0]})
            errors["imreg_dft.similarity"].append(abs(-float(peer["angle"]) - angle))  # imreg_dft: clockwise
        results[name] = {method: peers.summarize(values, FAILURE_DEG) for method, values in errors.items()}
        results[name]["semservo"]["worst_deg"] = [float(angle) for angle, error in zip(ANGLES, errors["semservo"])
                                                  if error > FAILURE_DEG]
        progress(f"rotation, {name}")
    return results


#: The turn under a view shift: turns within +-20 degrees (a run's start) and shifts of
#: the view up to a quarter of the field, in two random directions each.
SHIFT_FRACTIONS = (0.0, 0.05, 0.1, 0.15, 0.2, 0.25)
SHIFT_ANGLES = (-20.0, -7.5, -2.0, -0.4, 0.3, 1.2, 5.0, 12.0, 20.0)
SHIFT_DIRECTIONS = 2


def run_turn_under_shift(images: dict, rng, min_confidence: float, progress, peer: bool = True) -> dict:
    """The turn about the beam when the view has also moved (the first estimate of a run
    that starts far from the goal): the centred square (384 px, or half the image's
    shorter side) against itself turned by each angle and moved by each fraction of
    the field (``semservo.pairs.turned_and_moved``; the content entering beyond the
    image is mirrored), moderate noise. Per image and per fraction: error (degrees),
    semservo's refusals (confidence under ``min_confidence``) and wrong turns (> 1
    degree) it would act on; imreg_dft on the same pairs."""
    import imreg_dft

    results = {}
    electrons, read, _, _ = CONDITIONS["moderate noise"]
    for name, image in images.items():
        side = min(384, min(image.shape) // 2 * 2)
        reference = poisson_gaussian(centred_window(image, side), electrons, read, rng)
        ours = MotionEstimator(reference.copy())
        rows = {}
        for fraction in SHIFT_FRACTIONS:
            errors: dict[str, list[float]] = {"semservo": [], "imreg_dft.similarity": []}
            accepted, refused, wrong_acted_on, shift_errors = [], 0, 0, []
            for angle in SHIFT_ANGLES:
                for _ in range(SHIFT_DIRECTIONS if fraction else 1):
                    direction = rng.uniform(0, 2 * np.pi)
                    dx, dy = fraction * side * np.cos(direction), fraction * side * np.sin(direction)
                    current = poisson_gaussian(turned_and_moved(image, side, angle, dx, dy), electrons, read, rng)
                    motion = ours.estimate(current.copy())
                    error = abs((motion.rotation_deg - angle + 180) % 360 - 180)
                    errors["semservo"].append(error)
                    if motion.confidence >= min_confidence:
                        accepted.append(error)
                        wrong_acted_on += error > FAILURE_DEG
                        shift_errors.append(float(np.hypot(motion.dx - dx, motion.dy - dy)))
                    else:
                        refused += 1
                    if peer:
                        other = imreg_dft.similarity(reference.copy(), current.copy(), numiter=1,
                                                     constraints={"scale": [1, 0]})
                        errors["imreg_dft.similarity"].append(abs((-float(other["angle"]) - angle + 180) % 360 - 180))
            rows[f"{fraction:g}"] = {method: peers.summarize(values, FAILURE_DEG) for method, values in errors.items()
                                     if values}
            rows[f"{fraction:g}"]["semservo accepted"] = {
                **(peers.summarize(accepted, FAILURE_DEG) if accepted else {"mean": float("nan"), "max": float("nan")}),
                "refused": refused, "wrong_acted_on": int(wrong_acted_on),
                "shift_mean_px": float(np.mean(shift_errors)) if shift_errors else float("nan"),
                "shift_max_px": float(np.max(shift_errors)) if shift_errors else float("nan")}
        everything = [row["semservo accepted"] for row in rows.values()]
        results[name] = {"side_px": side, "fractions": rows}
        progress(f"turn under a view shift, {name}: worst mean of accepted "
                 f"{max(row['mean'] for row in everything):.3f} degree, refused {sum(r['refused'] for r in everything)}")
    return results


def run_consistency(progress) -> dict:
    before = grey(read_sem_image(find_sem_images() / "drift_pair_before.tif", data_bar=0).pixels)
    after = grey(read_sem_image(find_sem_images() / "drift_pair_after.tif", data_bar=0).pixels)
    # The drifted scan left 5 blank rows at the bottom and 3 blank columns on the left: both cut.
    before, after = before[:512, 8:-8], after[:512, 8:-8]
    results = {}
    for method, function in peers.TRANSLATION_METHODS.items():
        forward = np.array(function(before.copy(), after.copy()))
        backward = np.array(function(after.copy(), before.copy()))
        results[method] = {"A->B": forward.round(4).tolist(), "B->A": backward.round(4).tolist(),
                           "asymmetry_px": float(np.hypot(*(forward + backward)))}
    progress("consistency, drift pair")
    run = find_recorded_run()
    frames = [grey(read_sem_image(path).pixels)[6:-6, 6:-6] for path in sorted(run.glob("frame*.png"))]
    reference = grey(read_sem_image(run / "reference.png").pixels)[6:-6, 6:-6]
    for method, function in peers.TRANSLATION_METHODS.items():
        closures = []
        for a, b in zip(frames[:-1:3], frames[1::3]):
            ref_a = np.array(function(reference.copy(), a.copy()))
            a_b = np.array(function(a.copy(), b.copy()))
            ref_b = np.array(function(reference.copy(), b.copy()))
            closures.append(float(np.hypot(*(ref_a + a_b - ref_b))))
        results[method]["chain_2013_mean_px"] = float(np.mean(closures))
        results[method]["chain_2013_max_px"] = float(np.max(closures))
        asymmetries = [float(np.hypot(*(np.array(function(a.copy(), b.copy())) + np.array(function(b.copy(), a.copy())))))
                       for a, b in zip(frames[:-1:3], frames[1::3])]
        results[method]["asymmetry_2013_mean_px"] = float(np.mean(asymmetries))
        results[method]["asymmetry_2013_max_px"] = float(np.max(asymmetries))
    progress("consistency, 2013 chains")
    return results


def print_tables(results: dict) -> None:
    """The tables of the cases that ran, markdown."""
    methods = list(peers.TRANSLATION_METHODS)
    if "translation" in results:
        print("\n### Translation: mean error px (failures > 1 px) per image, all conditions")
        print("| image | set | pairs | " + " | ".join(methods) + " | bad acted on | good refused |")
        print("| --- " * (len(methods) + 5) + "|")
        for name, row in results["translation"].items():
            cells = [f"{row['methods'][m]['mean']:.3f} ({row['methods'][m]['failures']})" for m in methods]
            confidence = row["confidence"]
            print(f"| {name} | {'developed on' if name in TUNED_ON else 'held out'} | {row['pairs']} | " + " | ".join(cells)
                  + f" | {confidence['bad_acted_on']} | {confidence['good_refused']} of {confidence['good']} |")
    if "rotation" in results:
        print("\n### Rotation: mean error degrees (failures > 1 degree)")
        print("| image | semservo | imreg_dft | semservo's failures at |")
        print("| --- | --- | --- | --- |")
        for name, row in results["rotation"].items():
            ours, peer = row["semservo"], row["imreg_dft.similarity"]
            print(f"| {name} | {ours['mean']:.3f} ({ours['failures']}) | {peer['mean']:.3f} ({peer['failures']}) | "
                  f"{', '.join(f'{angle:g}' for angle in ours['worst_deg']) or '-'} |")
    if "translation_stress" in results:
        print("\n### Translation on a noisy, low-contrast frame: mean error px (failures > 1 px); semservo's failures"
              " acted on (confidence >= min_confidence) and refusals")
        print("| image | set | condition | pairs | " + " | ".join(methods) + " | semservo failures acted on | refused |")
        print("| --- " * (len(methods) + 6) + "|")
        for name, by_condition in results["translation_stress"].items():
            for condition, row in by_condition.items():
                cells = [f"{row['methods'][m]['mean']:.3f} ({row['methods'][m]['failures']})" for m in methods]
                print(f"| {name} | {'developed on' if name in TUNED_ON else 'held out'} | {condition} | {row['pairs']} | "
                      + " | ".join(cells) + f" | {row['semservo']['failures_acted_on']} | {row['semservo']['refused']} |")
    if "turn_under_shift" in results:
        print("\n### Turn about the beam under a view shift (degrees): mean / max error, semservo over the estimates it"
              " accepts, its refusals and wrong turns (> 1 degree) acted on; imreg_dft on the same pairs")
        fractions = list(next(iter(results["turn_under_shift"].values()))["fractions"])
        print("| image | set | side px | " + " | ".join(f"shift {float(f) * 100:g} %" for f in fractions)
              + " | refused | wrong acted on | imreg_dft (all shifts) |")
        print("| --- " * (len(fractions) + 6) + "|")
        for name, row in results["turn_under_shift"].items():
            cells, refused, wrong, peer = [], 0, 0, []
            for fraction in fractions:
                accepted = row["fractions"][fraction]["semservo accepted"]
                cells.append(f"{accepted['mean']:.3f} / {accepted['max']:.3f}")
                refused += accepted["refused"]
                wrong += accepted["wrong_acted_on"]
                if "imreg_dft.similarity" in row["fractions"][fraction]:
                    peer.append(row["fractions"][fraction]["imreg_dft.similarity"])
            peer_cell = (f"{np.mean([p['mean'] for p in peer]):.3f} ({sum(p['failures'] for p in peer)} > 1 degree)"
                         if peer else "-")
            print(f"| {name} | {'developed on' if name in TUNED_ON else 'held out'} | {row['side_px']} | "
                  + " | ".join(cells) + f" | {refused} | {wrong} | {peer_cell} |")
        print("\nThe shift of the same accepted estimates (px): mean / max")
        print("| image | " + " | ".join(f"shift {float(f) * 100:g} %" for f in fractions) + " |")
        print("| --- " * (len(fractions) + 1) + "|")
        for name, row in results["turn_under_shift"].items():
            cells = [f"{row['fractions'][f]['semservo accepted']['shift_mean_px']:.3f} / "
                     f"{row['fractions'][f]['semservo accepted']['shift_max_px']:.3f}" for f in fractions]
            print(f"| {name} | " + " | ".join(cells) + " |")
    if "confidence_stress" in results:
        electrons, read = STRESS
        print(f"\n### Confidence where estimates go wrong ({electrons} electrons per grey level, read noise {read};"
              " and scenes whose angle cannot be told)")
        print("| case | estimates | off by > 0.5 px (or > 1 degree) | of those acted on | good refused |")
        print("| --- | --- | --- | --- | --- |")
        for name, row in results["confidence_stress"].items():
            refused = "-" if row["good_refused"] is None else f"{row['good_refused']} of {row['good']}"
            print(f"| {name} | {row['estimates']} | {row['bad']} | {row['bad_acted_on']} | {refused} |")
    if "consistency" in results:
        print("\n### Self-consistency (px): |A->B + B->A| on the real drifted pair and on 2013 frame pairs;"
              " 2013 chains |ref->a + a->b - ref->b|")
        print("| method | drift pair A->B | its asymmetry | 2013 asymmetry mean | max | 2013 chains mean | max |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        for method, row in results["consistency"].items():
            print(f"| {method} | {row['A->B']} | {row['asymmetry_px']:.4f} | {row['asymmetry_2013_mean_px']:.4f} | "
                  f"{row['asymmetry_2013_max_px']:.4f} | {row['chain_2013_mean_px']:.4f} | "
                  f"{row['chain_2013_max_px']:.4f} |")


def print_timing(timing: dict) -> None:
    print("\n### Time per 512 x 512 frame of the 2013 run, one core (ratio to cv2.phaseCorrelate, paired per round)")
    print("| method | ms (median) | ratio (median) | ratio range over rounds |")
    print("| --- | --- | --- | --- |")
    for method, row in timing.items():
        low, high = row["ratio_range"]
        print(f"| {method} | {row['ms']:.2f} | {row['ratio']:.2f} | {low:.2f}-{high:.2f} |")


CASES = ("translation", "rotation", "confidence_stress", "consistency", "timing", "turn_under_shift",
         "translation_stress")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", type=int, default=4, help="pairs per block factor and image (default 4)")
    parser.add_argument("--seed", type=int, default=14)
    parser.add_argument("--only", nargs="+", choices=CASES, default=list(CASES),
                        help="run these cases only (each keeps the random draws it has in a full run)")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "sem_images.json")
    args = parser.parse_args(argv)
    started = time.monotonic()

    def progress(text: str) -> None:
        print(f"[{time.monotonic() - started:6.1f} s] {text}", flush=True)

    images = load_images()
    min_confidence = RunSettings().min_confidence
    # One generator per case, seeded from --seed and the case's name: a case's pairs do
    # not depend on which other cases run.
    def rng(case: str) -> np.random.Generator:
        return np.random.default_rng([args.seed, CASES.index(case)])

    runs = {
        "translation": lambda: run_translation(images, args.pairs, rng("translation"), min_confidence, progress),
        "rotation": lambda: run_rotation(images, rng("rotation"), progress),
        "confidence_stress": lambda: run_confidence_stress(images, args.pairs, rng("confidence_stress"),
                                                           min_confidence, progress),
        "consistency": lambda: run_consistency(progress),
        "timing": lambda: peers.timed_in_clean_process(argparse.Namespace(data=find_recorded_run(), repeats=15),
                                                       progress),
        "turn_under_shift": lambda: run_turn_under_shift(images, rng("turn_under_shift"), min_confidence, progress),
        "translation_stress": lambda: run_translation_stress(images, args.pairs, rng("translation_stress"),
                                                             min_confidence, progress),
    }
    results = {"tuned_on": list(TUNED_ON), "held_out": list(HELD_OUT), "min_confidence": min_confidence}
    for case in CASES:
        if case in args.only:
            results[case] = runs[case]()
    print_tables(results)
    if "timing" in results:
        print_timing(results["timing"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(jsontext.dumps(results, indent=2))
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
