"""``semservo reproduce``: the paper's experiments on the simulated lab, each table beside
the paper's own numbers, with the baselines it compared against closing the same loop.

Experiments (``--only`` takes these names):

* ``fig4``: the cost e'e (eq. 32) around the desired pose, semservo's and the photometric
  error's, as a map;
* ``table2``: positioning error against the quality of the desired image (reference
  dwell 4.3, 5.8, 8.6, 11.5 us/px; live frames at 360 ns/px);
* ``table3``: accuracy and its spread over trials for the six cases, RMSE and PSNR of the
  final against the desired image, the simulator's true error beside the image's;
* ``table4``: time per iteration (computation, and frames) and successes out of N for
  semservo and every baseline (:mod:`.methods`) on the six cases, the same starts;
* ``figs9_11``: error, cost and voltages per iteration for three trials per condition
  (from ``table3``'s trials);
* ``table1``: the tilts (Table I) on the paper's three poses (:mod:`.tilts`, which
  ``bench/tilt.py`` runs on 30 more);
* ``replay2013``: the real 2013 run (photometric servoing) replayed against our
  photometric baseline: its recorded increments against ours, per axis;
* ``fig8``: a 5-DOF run from (7, 12, 20) degrees (and three from random poses in the full
  run) through the whole stack, which the launcher starts on simulated hardware;
* ``time_to_target`` (not in the paper): fresh frames, frames scanned and simulated seconds
  to the target, true final error and converged of N, for the paper's law and the position
  law (:class:`semservo.control.PositionLaw`) side by side on a continuously scanning SEM
  (:func:`.loop.run_timed_trial`), per preset and offset (5, 15, 30 % of the field and
  half a pixel), with the stage's model calibrated, unknown (a linear model from the
  nominal stroke) or another stage's (+-15 %); and the photometric baseline's time to
  target (paper's law, the same budget);
* ``hold`` (not in the paper): a position held for 10 minutes of simulated time under the
  ``unstable`` preset's drift and vibration, the true error and the corrections made.

Results are kept per experiment in ``<out>/results/<name>.json``: a finished experiment is
skipped when the command runs again (``--fresh`` redoes it), so a long run can be
interrupted and resumed; ``time_to_target`` also keeps each trial as it finishes
(``<out>/results/time_to_target.partial.jsonl``, removed once the experiment's result is
written) and resumes mid-experiment. ``--quick`` runs a reduced version (fewer cases, trials and grid
points) in a few minutes on 2 cores.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Callable

import numpy as np

from semservo import jsontext
from semservo.reproduce import loop, methods, tilts

#: The paper's cases 1-6 (Table III, IV) as the fake lab's presets.
CASES = ("optimal", "noisy", "high-magnification", "unstable", "high-quality-reference", "mask-reference")
#: Table III: accuracy x, y (um), std x, y (um), RMSE, PSNR.
PAPER_TABLE3 = {
    "optimal": (0.11, 0.19, 0.0248, 0.0187, 1.60, 38.73), "noisy": (0.14, 0.23, 0.0108, 0.0216, 1.87, 32.70),
    "high-magnification": (0.04, 0.11, 0.0061, 0.0053, 1.79, 33.68),
    "unstable": (0.22, 0.37, 0.0147, 0.0286, None, None),
    "high-quality-reference": (0.09, 0.13, 0.0089, 0.0127, None, None),
    "mask-reference": (0.29, 0.47, 0.0497, 0.0589, None, None),
}
#: Table IV: ms per iteration (successes of 6; None: all 6 failed) for ours, flow, SURF, FAST.
PAPER_TABLE4 = {
    "optimal": ((38, 6), (29, 6), (911, 6), (73, 6)), "noisy": ((33, 6), (34, 6), (797, 4), (49, 2)),
    "high-magnification": ((37, 6), (30, 6), (1063, 6), (65, 5)),
    "unstable": ((38, 6), (None, 0), (None, 0), (None, 0)),
    "high-quality-reference": ((36, 6), (34, 5), (826, 3), (71, 4)),
    "mask-reference": ((39, 6), (33, 6), (None, 0), (None, 0)),
}
#: Table II: reference dwell (us/px) -> error x, y (px).
PAPER_TABLE2 = {4.3: (0.65, 0.81), 5.8: (0.48, 0.69), 8.6: (0.33, 0.51), 11.5: (0.26, 0.39)}
#: Table I: true (alpha, beta, gamma); the paper's measured values reach 0.82 degree off.
PAPER_TABLE1_POSES = tuple(tilts.PAPER_POSES)

EXPERIMENTS = ("fig4", "table2", "table3", "table4", "figs9_11", "table1", "fig8", "replay2013", "time_to_target",
               "hold")
#: Figs. 9-11 also show the calibration sample (the paper's case 7, Fig. 11): run with Table III's trials.
FIGURE_CASES = CASES + ("repeated-pattern",)


def starts(count: int, seed: int, field_um: float) -> list[tuple[float, float]]:
    """Starting displacements: 8-15 % of the field (41-77 px) in a random direction, the same for
    every method."""
    rng = np.random.default_rng(seed)
    radius = rng.uniform(0.08, 0.15, count) * field_um
    angle = rng.uniform(0, 2 * np.pi, count)
    return [(float(r * np.cos(a)), float(r * np.sin(a))) for r, a in zip(radius, angle)]


def field_um(case: str) -> float:
    return loop.Lab(case, 0).pixel_um * 512


class Progress:
    """A progress bar per experiment, with the time left (tqdm) on a terminal; elsewhere (a
    log file, CI) a plain line at most every ``LINE_EVERY_S`` and at the end, not a bar's
    carriage returns."""

    #: Seconds between two progress lines when the output is not a terminal.
    LINE_EVERY_S = 30.0

    def __init__(self, name: str, total: int, quiet: bool = False, stream=None):
        import sys
        import time

        self.name, self.total, self.done, self.quiet = name, total, 0, quiet
        self.stream = stream or sys.stderr
        self.clock = time.monotonic
        self.started = self.last_line = self.clock()
        self.bar = None
        if not quiet and getattr(self.stream, "isatty", lambda: False)():
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=f"{name:9s}", unit="trial", dynamic_ncols=True, file=self.stream,
                            bar_format="{desc} {bar} {n_fmt}/{total_fmt} [{elapsed}<{remaining}] {postfix}")

    def step(self, note: str = "") -> None:
        self.done += 1
        if self.bar is not None:
            self.bar.set_postfix_str(note[:60])
            self.bar.update(1)
        elif not self.quiet and (self.clock() - self.last_line >= self.LINE_EVERY_S or self.done == self.total):
            self.last_line = self.clock()
            elapsed = self.last_line - self.started
            left = elapsed / self.done * (self.total - self.done)
            print(f"{self.name}: {self.done}/{self.total} after {elapsed:.0f} s, about {left:.0f} s left"
                  + (f" ({note[:60]})" if note else ""), file=self.stream, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# -- the experiments ------------------------------------------------------------------

#: Table IV: every method gets the same budget of simulated time (scans), not a number of
#: iterations; 150 s is 330 frames at 720 ns/px, 1200 at 180 ns/px.
TABLE4_BUDGET_S = 150.0
TABLE4_SETTINGS = loop.TrialSettings(max_iterations=100_000, time_budget_s=TABLE4_BUDGET_S)
#: A run that stopped within tolerance by its own measure is at the target when the
#: simulator's true error is under this (px); else it converged falsely (a photometric
#: step vanishes in a flat valley of its cost far from the goal).
AT_TARGET_PX = 1.0


def experiment_table4(quick: bool, progress: Callable[[int], Progress]) -> dict:
    cases = ("optimal", "noisy", "unstable") if quick else CASES
    trials = 1 if quick else 6
    rows = {}
    bar = progress(len(cases) * len(methods.METHODS) * trials)
    for case in cases:
        for start_index, start in enumerate(starts(trials, 4, field_um(case))):
            for method in methods.METHODS:
                result = loop.run_trial(case, method, start, seed=100 + start_index, settings=TABLE4_SETTINGS)
                rows.setdefault(case, {}).setdefault(method, []).append(_summary(result))
                bar.step(f"{case} {method}: {result['outcome']}")
    bar.close()
    return {"cases": list(cases), "trials": trials, "rows": rows, "budget_s": TABLE4_BUDGET_S,
            "at_target_px": AT_TARGET_PX}


def experiment_table3(quick: bool, progress: Callable[[int], Progress]) -> dict:
    trials = 1 if quick else 10
    rows = {}
    bar = progress(len(FIGURE_CASES) * trials)
    for case in FIGURE_CASES:
        for index, start in enumerate(starts(trials, 3, field_um(case))):
            result = loop.run_trial(case, "semservo", start, seed=200 + index, keep_images=True)
            summary = _summary(result)
            if case in ("optimal", "noisy", "high-magnification"):
                summary["rmse"], summary["psnr_db"] = loop.rmse_psnr(result["desired"], result["final"])
            if index < 3:  # the trials Figs. 9-11 plot
                summary["records"] = [{key: value for key, value in record.items() if key != "compute_ms"}
                                      for record in result["records"]]
            rows.setdefault(case, []).append(summary)
            bar.step(f"{case}: {result['outcome']} {result['true_error_px']:.2f} px")
    bar.close()
    return {"trials": trials, "rows": rows}


def experiment_table2(quick: bool, progress: Callable[[int], Progress]) -> dict:
    trials = 1 if quick else 5
    rows = {}
    bar = progress(len(PAPER_TABLE2) * trials)
    for dwell_us in PAPER_TABLE2:
        for index, start in enumerate(starts(trials, 2, field_um("high-quality-reference"))):
            result = loop.run_trial("high-quality-reference", "semservo", start, seed=300 + index,
                                    reference_dwell_ns=dwell_us * 1000)
            rows.setdefault(str(dwell_us), []).append(_summary(result))
            bar.step(f"{dwell_us} us/px: {result['true_error_px']:.2f} px")
    bar.close()
    return {"trials": trials, "rows": rows}


def experiment_fig4(quick: bool, progress: Callable[[int], Progress]) -> dict:
    """e'e of semservo's measured error and of the photometric error (I - I*) for stage
    displacements on a grid about the desired pose (the paper's Fig. 4)."""
    from semservo.simulation.sem import Pose

    lab = loop.Lab("optimal", 5)
    reference, _ = lab.scan()
    semservo = methods.make("semservo", reference)
    desired = methods._normalised(reference, 2)
    points = 9 if quick else 21
    offsets_px = np.linspace(-60, 60, points)
    bar = progress(points)
    fourier, photometric = np.zeros((points, points)), np.zeros((points, points))
    for row, dy in enumerate(offsets_px):
        for col, dx in enumerate(offsets_px):
            pose = Pose(x_um=dx * lab.pixel_um, y_um=dy * lab.pixel_um)
            frame = lab.world.sem.render(lab.settings, [pose] * 512, [pose] * 512, lab.world.rng)
            measured = semservo(frame)
            fourier[row, col] = measured.dx ** 2 + measured.dy ** 2 if measured.ok else np.nan
            difference = methods._normalised(frame, 2) - desired
            photometric[row, col] = float(np.mean(difference ** 2))
        bar.step(f"row {row + 1}")
    bar.close()
    return {"offsets_px": offsets_px.tolist(), "fourier": fourier.tolist(), "photometric": photometric.tolist()}


def experiment_table1(quick: bool, progress: Callable[[int], Progress]) -> dict:
    """The paper's Table I: its three poses, both tilt methods and gamma (:mod:`.tilts`)."""
    bar = progress(len(PAPER_TABLE1_POSES))
    table = tilts.table_one(list(PAPER_TABLE1_POSES), seed=15, say=lambda text: bar.step("pose"))
    bar.close()
    return {"rows": table["rows"], "taught": table["taught"]}


def experiment_fig8(quick: bool, progress: Callable[[int], Progress]) -> dict:
    """The paper's Fig. 8: a 5-DOF run from (7, 12, 20) degrees plus a translation, and
    (full run) three more from random poses, through the whole stack (started here on
    simulated hardware, on fresh loopback ports), with :func:`.tilts.five_dof_runs`."""
    initial = [tilts.FIG8_START] + tilts.random_starts(np.random.default_rng(8), 0 if quick else 3)
    bar = progress(len(initial))
    runs = tilts.five_dof_runs(initial, speedup=20.0, say=lambda text: bar.step("run"))
    bar.close()
    # The first run's iterations are plotted; the others are summarized.
    return {"runs": [run if index == 0 else {key: value for key, value in run.items() if key != "trajectory"}
                     for index, run in enumerate(runs)]}


def experiment_replay2013(quick: bool, progress: Callable[[int], Progress]) -> dict:
    """The check the issue asks of the photometric baseline: the real 2013 run was driven
    by photometric visual servoing, so its recorded stage increments per iteration should
    follow what our photometric method computes from the same frames (up to a gain and
    the axes' signs). semservo's measured error per frame goes beside, as the run's path."""
    from semservo.config import find_recorded_run
    from semservo.imagefiles import list_frames, read_image

    folder = find_recorded_run()
    if not (folder / "reference.png").is_file():
        return {"skipped": f"the 2013 recording is not at {folder}"}
    reference = read_image(folder / "reference.png")[0].astype(np.float32)
    frames = [read_image(path)[0].astype(np.float32) for path in list_frames(folder, "frame*")]
    recorded = {axis: np.loadtxt(folder / f"result_{axis}_voltage.txt", comments=";", usecols=(0, 1, 2, 3))
                for axis in ("x", "y")}
    photometric, fourier = methods.make("photometric", reference), methods.make("semservo", reference)
    bar = progress(len(frames))
    ours, measured = [], []
    for frame in frames:
        step, motion = photometric(frame), fourier(frame)
        ours.append((step.dx, step.dy))
        measured.append((motion.dx, motion.dy))
        bar.step()
    bar.close()
    ours = np.array(ours)
    result = {"frames": len(frames), "ours_px": ours.tolist(), "semservo_px": np.array(measured).tolist(),
              "recorded_increment_um": {axis: table[:, 1].tolist() for axis, table in recorded.items()}}
    # Row k+1 of the recording is the move made after frame k (about one frame of delay).
    measured = np.array(measured)
    for index, axis in enumerate(("x", "y")):
        increments = recorded[axis][1:, 1]
        count = min(len(increments), len(ours))
        for label, start in (("", 0), ("_last", max(count - 23, 0))):
            result[f"correlation_{axis}{label}"] = float(np.corrcoef(ours[start:count, index],
                                                                     increments[start:count])[0, 1])
            result[f"error_correlation_{axis}{label}"] = float(np.corrcoef(measured[start:count, index],
                                                                           increments[start:count])[0, 1])
    return result


#: Time to target: the offsets, as fractions of the field, and "under a pixel" (0.5 px).
TIME_OFFSETS = (0.05, 0.15, 0.30, "0.5 px")
#: The laws side by side, and the photometric baseline (its measurement, the paper's law).
TIME_LAWS = (("position", "semservo"), ("paper", "semservo"), ("paper", "photometric"))
#: What each law acts on by default (the controller's ``partial_frames``): the position
#: law on partial frames (the rows of the scan a move lands in, scanned after it settled),
#: the paper's law on whole fresh frames (its velocity law moves v t per frame, so more
#: frequent frames do not bring it sooner). Each law is also run the other way (calibrated
#: model), so the comparison takes each at its best.
LAW_FRAMES = {"position": "partial", "paper": "whole"}
OTHER_FRAMES = {"partial": "whole", "whole": "partial"}


#: The paper's law runs with these stage models (the position law with all of them), the
#: uncalibrated one on fewer trials per cell (its gain adapts; the targets are the
#: position law's); the photometric baseline from 15 % of the field (the paper's starts
#: are 8-15 %), on fewer trials: both to keep the run within hours on a shared machine.
PAPER_LAW_MODELS = ("calibrated", "uncalibrated")
PAPER_UNCALIBRATED_TRIALS = 3
BASELINE_OFFSETS, BASELINE_TRIALS = (0.15,), 5


def time_to_target_trials(quick: bool, *, trials: int | None = None, cases=None, models=None,
                          baseline: bool = True, offsets=TIME_OFFSETS) -> list[dict]:
    """The trials of ``time_to_target``, each a dict of ``run_timed_trial``'s arguments and
    its key: every preset, offset and trial, the position law with every stage model, the
    paper's law with :data:`PAPER_LAW_MODELS` (the same start and seed for each), the
    photometric baseline (paper's law, calibrated) at :data:`BASELINE_OFFSETS`."""
    cases = cases or (("optimal", "high-magnification") if quick else FIGURE_CASES)
    models = models or (("calibrated", "uncalibrated") if quick else loop.STAGE_MODELS)
    trials = trials or (2 if quick else 10)
    jobs = []
    for case in cases:
        field = field_um(case)
        pixel = field / 512
        for offset_index, offset in enumerate(TIME_OFFSETS):
            if offset not in offsets:
                continue
            radius = 0.5 * pixel if offset == "0.5 px" else offset * field
            for trial in range(trials):
                angle = np.random.default_rng([2028, offset_index, trial]).uniform(0, 2 * np.pi)
                start = (float(radius * np.cos(angle)), float(radius * np.sin(angle)))
                for law, method in TIME_LAWS:
                    if method == "photometric":
                        if not baseline or offset not in BASELINE_OFFSETS or trial >= BASELINE_TRIALS:
                            continue
                        chosen = ("calibrated",)
                    else:
                        chosen = [m for m in models if law == "position" or m == "calibrated"
                                  or (m in PAPER_LAW_MODELS and trial < PAPER_UNCALIBRATED_TRIALS)]
                    default = LAW_FRAMES[law] if method == "semservo" else "whole"
                    runs = [(model, default) for model in chosen]
                    if method == "semservo" and "calibrated" in chosen:
                        runs.append(("calibrated", OTHER_FRAMES[default]))
                    for model, frames in runs:
                        key = f"{case}|{offset}|{trial}|{law}|{method}|{model}|{frames}"
                        jobs.append({"key": key, "case": case, "offset": offset, "trial": trial, "law": law,
                                     "method": method, "stage_model": model, "frames": frames, "start_um": start,
                                     "seed": 600 + trial})
    return jobs


def time_trial(job: dict, taught: loop.Taught | None = None) -> dict:
    """One ``time_to_target`` trial (module level: worker processes call it)."""
    frames = job.get("frames", "whole")
    settings = loop.TimedSettings(time_budget_s=TIME_BUDGET_S, partial_frames=frames == "partial")
    result = loop.run_timed_trial(job["case"], job["law"], tuple(job["start_um"]), seed=job["seed"],
                                  stage_model=job["stage_model"], method=job["method"], settings=settings,
                                  taught=taught)
    keep = ("outcome", "reason", "fresh_frames", "frames_scanned", "seconds", "iterations", "true_error_px",
            "stage_error_px", "overshoot_px", "frame_time_s", "pixel_um")
    summary = {key: job[key] for key in ("key", "case", "offset", "trial", "law", "method", "stage_model")}
    summary.update({key: result[key] for key in keep}, frames=frames,
                   partial_frames_used=sum(1 for record in result["records"] if record.get("first_row")))
    if job["trial"] == 0 and job["stage_model"] == "calibrated":
        summary["trace"] = [(round(t, 3), round(error, 4), fresh) for t, error, fresh in result["trace"]]
    return summary


def time_trials(group: list[dict]) -> list[dict]:
    """Trials of one preset and seed, taught once."""
    first = group[0]
    taught = loop.teach(loop.Lab(first["case"], first["seed"]), loop.TimedSettings())
    return [time_trial(job, taught) for job in group]


#: Every law and method gets the same simulated time to reach the target (the paper's
#: law needs up to ~60 s from 30 % of the field at x5000).
TIME_BUDGET_S = 150.0


def experiment_time_to_target(quick: bool, progress: Callable[[int], Progress], *, checkpoint: Path | None = None,
                              workers: int = 1, trials: int | None = None, cases=None, models=None,
                              baseline: bool = True, offsets=TIME_OFFSETS) -> dict:
    """Time to target (module docstring); each finished trial is appended to ``checkpoint``
    and skipped when the experiment runs again; ``workers`` processes run trials at once."""
    jobs = time_to_target_trials(quick, trials=trials, cases=cases, models=models, baseline=baseline, offsets=offsets)
    done = {}
    if checkpoint is not None and checkpoint.is_file():
        for line in checkpoint.read_text().splitlines():
            if line.strip():
                row = json.loads(line)
                done[row["key"]] = row
    pending = [job for job in jobs if job["key"] not in done]
    bar = progress(len(jobs))
    for _ in range(len(jobs) - len(pending)):
        bar.step("kept")

    def keep(row: dict) -> None:
        done[row["key"]] = row
        if checkpoint is not None:
            with checkpoint.open("a") as file:
                file.write(jsontext.dumps(row) + "\n")
        bar.step(f"{row['case']} {row['law']}/{row['method']} {row['stage_model']}: {row['fresh_frames']} frames")

    # Trials of one preset and seed share what teaching left (the same lab until the jog).
    groups = {}
    for job in pending:
        groups.setdefault((job["case"], job["seed"]), []).append(job)
    if workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers) as pool:
            for rows in pool.map(time_trials, groups.values()):
                for row in rows:
                    keep(row)
    else:
        for group in groups.values():
            for row in time_trials(group):
                keep(row)
    bar.close()
    rows = [done[job["key"]] for job in jobs]
    return {"offsets": [offset for offset in TIME_OFFSETS if offset in offsets], "trials": max(job["trial"] for job in jobs) + 1,
            "cases": list(dict.fromkeys(job["case"] for job in jobs)),
            "models": list(dict.fromkeys(job["stage_model"] for job in jobs)),
            "settings": {**loop.asdict(loop.TimedSettings(time_budget_s=TIME_BUDGET_S))}, "rows": rows}


def experiment_hold(quick: bool, progress: Callable[[int], Progress]) -> dict:
    """Hold after arrival: the position law converges from 5 % of the field under the
    ``unstable`` preset (on partial frames, its default), then holds for 10 simulated
    minutes (1 in a quick run); the true error of every fresh frame while holding and the
    corrections made."""
    minutes = 1.0 if quick else 10.0
    runs = []
    bar = progress(2)
    for seed, angle in ((700, 0.4), (701, 2.5)):
        radius = 0.05 * field_um("unstable")
        result = loop.run_timed_trial("unstable", "position", (radius * math.cos(angle), radius * math.sin(angle)),
                                      seed=seed, settings=loop.TimedSettings(hold_s=60.0 * minutes,
                                                                             partial_frames=True))
        frames = [(t, error) for t, error, fresh in result["trace"] if fresh]
        runs.append({key: result.get(key) for key in ("outcome", "reason", "fresh_frames", "seconds", "true_error_px",
                                                      "hold_s", "hold_corrections", "hold_worst_true_px",
                                                      "frame_time_s", "pixel_um")}
                    | {"trace": [(round(t, 2), round(e, 4)) for t, e in frames]})
        bar.step(f"worst {result.get('hold_worst_true_px', math.nan):.3f} px")
    bar.close()
    return {"minutes": minutes, "runs": runs}


def _summary(result: dict) -> dict:
    last = next((r for r in reversed(result["records"]) if "error_px" in r), {})
    return {key: result[key] for key in ("outcome", "reason", "iterations", "true_error_um", "true_error_px",
                                         "compute_ms", "frame_time_s", "start_um", "pixel_um")} | {
        "measured_error_px": last.get("error_px")}


RUNNERS = {"fig4": experiment_fig4, "table2": experiment_table2, "table3": experiment_table3,
           "table4": experiment_table4, "table1": experiment_table1, "fig8": experiment_fig8,
           "replay2013": experiment_replay2013, "time_to_target": experiment_time_to_target,
           "hold": experiment_hold}


def run(out: Path, *, quick: bool = False, only: list[str] | None = None, fresh: bool = False,
        quiet: bool = False, say: Callable[[str], None] = print) -> Path:
    """Run the experiments (``only``: a subset) into ``out``; returns the report's path."""
    from semservo.reproduce import report

    unknown = set(only or ()) - set(EXPERIMENTS)
    if unknown:
        raise ValueError(f"unknown experiments {sorted(unknown)}; experiments: {', '.join(EXPERIMENTS)}")
    results_dir = out / "results"
    results_dir.mkdir(parents=True, exist_ok=True)
    chosen = [name for name in EXPERIMENTS if not only or name in only]
    for name in chosen:
        if name == "figs9_11":
            continue  # drawn from table3's trials
        path = results_dir / f"{name}.json"
        if path.is_file() and not fresh:
            kept = json.loads(path.read_text())
            if kept.get("quick") == quick:
                say(f"{name}: kept from an earlier run ({path}); --fresh runs it again")
                continue
        started = time.monotonic()
        extra = {}
        if name == "time_to_target":
            checkpoint = results_dir / f"time_to_target{'.quick' if quick else ''}.partial.jsonl"
            if fresh and checkpoint.is_file():
                checkpoint.unlink()
            extra = {"checkpoint": checkpoint}
        result = RUNNERS[name](quick, lambda total, name=name: Progress(name, total, quiet), **extra)
        result.update(quick=quick, seconds=round(time.monotonic() - started, 1),
                      finished_at=time.strftime("%Y-%m-%d %H:%M:%S"))
        path.write_text(jsontext.dumps(result))
        if "checkpoint" in extra:
            extra["checkpoint"].unlink(missing_ok=True)  # its trials are in the result now
        say(f"{name}: done in {result['seconds']:.0f} s")
    return report.write(out, say=say)


def load(out: Path, name: str) -> dict | None:
    path = out / "results" / f"{name}.json"
    return json.loads(path.read_text()) if path.is_file() else None

