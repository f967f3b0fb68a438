"""The whole-frame shift beside the one averaged over the scan's bands of rows.

``./dev bench scan_averaged``: the whole-frame shift beside the one averaged over the
scan's bands of rows (``MotionEstimator(scan_averaged=True)``, :mod:`semservo.estimation.raster`).

1. At rest: per preset, ``--seeds`` labs of the simulated lab, each teaching a reference
   of 4 frames (and the vibration lines from 4 more at rest) and measuring ``--frames``
   more; the error of each estimate (the whole frame, the bands' mean, the vibration
   lines' fit) against the simulator's pose averaged over that frame's scan (RMS over
   both axes, px), per seed. ``--wander``: also with vibration lines whose phase wanders
   (another vibration than the simulator's steady tones, which the lines' fit assumes),
   reported apart.
2. With ``--closed-loop``: the position law's time to target (the timed trials of
   ``./dev bench time_to_target``, calibrated stage, 10 starts per offset) at x5000, or
   at every preset of ``--closed-loop-presets``, once with each estimate: fresh frames
   median and worst, true final error worst, converged of N.
3. The real drift pair (no truth): how well A -> B -> A closes with each.

    ./dev bench scan_averaged                      # at rest, x5000 and x1200: ~2 min
    ./dev bench scan_averaged --closed-loop        # plus 120 timed trials: ~5 min more
    ./dev bench scan_averaged --wander 0 0.5 1.7   # steady, then wandering lines
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from semservo import reproduce
from semservo.config import find_sem_images
from semservo.estimation import MotionEstimator
from semservo.imagefiles import read_image
from semservo.reproduce import loop


ESTIMATES = ("whole frame", "bands' mean", "vibration lines")


def at_rest(case: str, seeds: range, frames: int, wander: float = 0.0) -> dict[str, list[float]]:
    """Per seed, the RMS error (px) of the whole-frame estimate, the bands' mean and the
    vibration lines' fit (lines learned at the teach, from its 4 frames at rest)."""
    errors = {name: [] for name in ESTIMATES}
    for seed in seeds:
        lab = loop.Lab(case, seed, phase_walk_rad_per_sqrt_s=wander)
        taught = loop.teach(lab, loop.TimedSettings())  # the timed trials' reference, pose and lines
        lines = MotionEstimator(taught.reference, rotation=False, scan_averaged=True)
        lines.vibration_hz = taught.vibration_hz
        estimators = {"whole frame": MotionEstimator(taught.reference, rotation=False),
                      "bands' mean": MotionEstimator(taught.reference, rotation=False, scan_averaged=True),
                      "vibration lines": lines}
        seen = {name: [] for name in estimators}
        for _ in range(frames):
            frame, interval = lab.scan()
            truth = (lab.true_pose(interval) - np.array(taught.taught_um)) / lab.pixel_um
            for name, estimator in estimators.items():
                motion = estimator.estimate(frame, line_time_s=lab.settings.line_time_s)
                seen[name].append((motion.dx - truth[0], motion.dy - truth[1]))
        for name, values in seen.items():
            errors[name].append(float(np.sqrt(np.mean(np.square(values)))))
        print(f"    seed {seed}: lines learned {', '.join(f'{value:.2f}' for value in taught.vibration_hz) or 'none'} Hz",
              flush=True)
    return errors


def closed_loop(case: str, trials: int, wander: float = 0.0) -> dict[str, dict]:
    """The position law's timed trials at ``case`` with each estimate."""
    jobs = [job for job in reproduce.time_to_target_trials(False, trials=trials, cases=[case], models=["calibrated"],
                                                           baseline=False) if job["law"] == "position"]
    outcome = {}
    for name in ESTIMATES:
        settings = loop.TimedSettings(time_budget_s=reproduce.TIME_BUDGET_S, scan_averaged=name != "whole frame",
                                      vibration_lines=name == "vibration lines", phase_walk_rad_per_sqrt_s=wander)
        taught, results = {}, []
        for job in jobs:
            if job["seed"] not in taught:
                taught[job["seed"]] = loop.teach(loop.Lab(case, job["seed"], phase_walk_rad_per_sqrt_s=wander), settings)
            result = loop.run_timed_trial(case, "position", tuple(job["start_um"]), seed=job["seed"],
                                          settings=settings, taught=taught[job["seed"]])
            results.append(result)
            print(".", end="", flush=True)
        frames = [result["fresh_frames"] for result in results]
        outcome[name] = {
            "median": float(np.median(frames)), "worst": int(max(frames)),
            "true_error_worst_px": max(result["true_error_px"] for result in results),
            "converged": sum(result["outcome"] == "converged" for result in results), "trials": len(results)}
    print()
    return outcome


def drift_pair_closure(folder: Path) -> dict[str, float] | None:
    before, after = folder / "drift_pair_before.tif", folder / "drift_pair_after.tif"
    if not (before.is_file() and after.is_file()):
        return None
    # Both scans whole (no data bar to crop; the automatic crop cut them differently).
    first, second = (read_image(path, data_bar=0)[0].astype(np.float32) for path in (before, after))
    closure = {}
    for averaged, name in ((False, "whole frame"), (True, "bands' mean")):
        forth = MotionEstimator(first, rotation=False, scan_averaged=averaged).estimate(second)
        back = MotionEstimator(second, rotation=False, scan_averaged=averaged).estimate(first)
        closure[name] = float(np.hypot(forth.dx + back.dx, forth.dy + back.dy))
    return closure


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--presets", nargs="+", default=["high-magnification", "optimal"], choices=list(reproduce.FIGURE_CASES))
    parser.add_argument("--seeds", type=int, default=10, help="labs per preset (default 10)")
    parser.add_argument("--frames", type=int, default=10, help="frames at rest per lab (default 10)")
    parser.add_argument("--closed-loop", action="store_true", help="also the position law's timed trials at x5000")
    parser.add_argument("--trials", type=int, default=10, help="closed loop: starts per offset (default 10)")
    parser.add_argument("--closed-loop-presets", nargs="+", default=["high-magnification"],
                        choices=list(reproduce.FIGURE_CASES), help="closed loop: the presets (default x5000)")
    parser.add_argument("--sem-images", type=Path, default=None,
                        help="the real images' folder (default: the shared data, or SEMSERVO_SEM_IMAGES)")
    parser.add_argument("--wander", nargs="+", type=float, default=[0.0],
                        help="the vibration lines' phase walk, radians per sqrt(s), one run each (default 0: the "
                             "simulator's steady tones; e.g. 0.5 and 1.7 wander 0.3 and 1 radian over a x5000 scan)")
    parser.add_argument("--skip-at-rest", action="store_true", help="only the closed loop (with --closed-loop)")
    args = parser.parse_args(argv)

    for wander in args.wander:
        kind = "steady tones" if wander == 0 else f"lines wandering {wander:g} rad/sqrt(s)"
        if not args.skip_at_rest:
            print(f"At rest, {kind}: RMS error against the simulator's pose over each scan (px), per seed")
            for case in args.presets:
                errors = at_rest(case, range(600, 600 + args.seeds), args.frames, wander)
                for name, values in errors.items():
                    print(f"  {case:20s} {name:16s} all {np.sqrt(np.mean(np.square(values))):.3f}  per seed "
                          + " ".join(f"{value:.3f}" for value in values))
        if args.closed_loop:
            for case in args.closed_loop_presets:
                print(f"Closed loop, {case}, {kind} (position law, calibrated):")
                for name, row in closed_loop(case, args.trials, wander).items():
                    print(f"  {name:16s} fresh frames median {row['median']:g}, worst {row['worst']}; true final "
                          f"error worst {row['true_error_worst_px']:.3f} px; converged {row['converged']}/{row['trials']}")
    closure = drift_pair_closure(args.sem_images or find_sem_images())
    if closure:
        print("Real drift pair, A -> B -> A closes to (px): "
              + ", ".join(f"{name} {value:.3f}" for name, value in closure.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
