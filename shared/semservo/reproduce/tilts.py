"""The tilts, measured (paper Table I and Fig. 8, issue #15): the library behind
``bench/tilt.py`` and ``semservo reproduce --only table1 fig8``.

* :func:`table_one`: alpha (about x), beta (about y) and gamma (about the beam) measured
  on the simulated SEM's ``tilts`` preset (x3000, a 3.5 um depth of field, gold on carbon)
  against a reference taught at (0, 0, 0). For each pose, the tilts by both methods from
  the same focus sweeps: the robust plane fit (semservo's default) and the paper's
  extended Gaussian image correlation (eq. 14-17), first from a wide sweep (nothing
  known), then from a tracking sweep planned from the first measurement on the taught
  sweep's grid; gamma from one frame at the nominal focus, raw and with the measured
  tilts' foreshortening undone; frames, simulated scan time and compute time.
* :func:`depth_of_field_scan`: how the plane fit's error grows with the depth of field.
* :func:`five_dof_runs`: 5-DOF runs through the whole stack (real services on loopback,
  the fake lab sped up), with the true final errors from the simulator;
  :func:`plot_fig8` plots one like the paper's Fig. 8.

Tuning caveat: the simulator and the methods were developed together, on this one
simulated scene; these are simulated results, not a real instrument's.
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable

import numpy as np

from semservo.config import EstimatorSettings
from semservo.estimation import MotionEstimator
from semservo.estimation.tilt import depth_map, egi_tilt_between, estimate_tilt, plan_sweep, undo_foreshortening
from semservo.simulation.sem import Pose, ScanSettings
from semservo.simulation.world import PRESETS, World

#: Paper Table I's three poses, (alpha, beta, gamma) in degrees.
PAPER_POSES = [(15.0, -15.0, 70.0), (8.0, -8.0, 30.0), (3.0, 3.0, -5.0)]
#: Paper Table I: the errors it reports reach 0.82 degree, with a sign flip at 3 degrees.
PAPER_WORST_DEG = 0.82
#: The depth of field the sweeps are planned with: the estimator service's default, which
#: is the ``tilts`` preset's (400 um aperture at 5 mm).
DEPTH_OF_FIELD_UM = EstimatorSettings.model_fields["tilt_depth_of_field_um"].default
#: Fig. 8's start: (alpha, beta, gamma) in degrees, (x, y) in um.
FIG8_START = (7.0, 12.0, 20.0, 3.0, -2.0)


def random_starts(rng: np.random.Generator, count: int) -> list[tuple[float, float, float, float, float]]:
    """``count`` random 5-DOF starts: tilts within +-10 degrees, gamma within +-20, x and y
    within +-4 um."""
    return [(float(rng.uniform(-10, 10)), float(rng.uniform(-10, 10)), float(rng.uniform(-20, 20)),
             float(rng.uniform(-4, 4)), float(rng.uniform(-4, 4))) for _ in range(count)]


class Lab:
    """The tilts preset's SEM, imaged at static poses."""

    def __init__(self, seed: int = 2013):
        self.world = World(PRESETS["tilts"], speedup=1000.0, seed=seed)
        self.settings = ScanSettings(dwell_ns=PRESETS["tilts"].dwell_ns, magnification=PRESETS["tilts"].magnification)
        self.pixel_um = self.settings.pixel_um
        self.field_um = self.settings.cols * self.pixel_um
        self.rng = np.random.default_rng(seed)

    def frame(self, pose: Pose, working_distance_um: float = 0.0) -> np.ndarray:
        settings = replace(self.settings, working_distance_um=working_distance_um)
        return self.world.sem.render(settings, [pose] * settings.rows, [pose] * settings.rows, self.rng)

    def sweep(self, pose: Pose, working_distances) -> np.ndarray:
        return np.stack([self.frame(pose, distance) for distance in working_distances])


def table_one(poses: list[tuple[float, float, float]], seed: int, say: Callable[[str], None] = print) -> dict:
    """Table I on ``poses`` ((alpha, beta, gamma) in degrees), each against a reference
    taught at (0, 0, 0): per pose, the errors (measured - true) of both methods, signs,
    frames, simulated scan time and compute time (see the module's text)."""
    lab = Lab(seed)
    reference_sweep = plan_sweep(0.0, DEPTH_OF_FIELD_UM, lab.field_um)
    grid = (reference_sweep[0], reference_sweep[1] - reference_sweep[0])
    taught_sweep = lab.sweep(Pose(), reference_sweep)
    taught = estimate_tilt(taught_sweep, reference_sweep, lab.pixel_um)
    taught_depths = depth_map(taught_sweep, reference_sweep)
    reference_frame = lab.frame(Pose())
    rotation = MotionEstimator(reference_frame, rotation=True)
    frame_time = lab.settings.frame_time_s
    rows = []
    started = time.monotonic()
    for index, (alpha, beta, gamma) in enumerate(poses, 1):
        pose = Pose(tilt_x_deg=alpha, tilt_y_deg=beta, rotation_deg=gamma)
        first_sweep = plan_sweep(taught.centre_depth, DEPTH_OF_FIELD_UM, lab.field_um, grid=grid,
                                 max_tilt_deg=15.0 + max(abs(taught.alpha_deg), abs(taught.beta_deg)))
        frames = lab.sweep(pose, first_sweep)
        clock = time.perf_counter()
        plane = estimate_tilt(frames, first_sweep, lab.pixel_um)
        plane_ms = (time.perf_counter() - clock) * 1e3
        clock = time.perf_counter()
        egi_alpha, egi_beta, _ = egi_tilt_between(taught_depths, depth_map(frames, first_sweep), 32, lab.pixel_um)
        egi_ms = (time.perf_counter() - clock) * 1e3
        tracking_sweep = plan_sweep(plane.centre_depth, DEPTH_OF_FIELD_UM, lab.field_um,
                                    tilt_deg=(plane.alpha_deg, plane.beta_deg), grid=grid)
        tracked = estimate_tilt(lab.sweep(pose, tracking_sweep), tracking_sweep, lab.pixel_um)
        nominal = lab.frame(pose)
        raw = rotation.estimate(nominal).rotation_deg
        measured_alpha, measured_beta = plane.alpha_deg - taught.alpha_deg, plane.beta_deg - taught.beta_deg
        compensated = rotation.estimate(undo_foreshortening(nominal, measured_alpha, measured_beta)).rotation_deg
        rows.append({
            "pose": [alpha, beta, gamma],
            "plane": [measured_alpha - alpha, measured_beta - beta],
            "plane_tracking": [tracked.alpha_deg - taught.alpha_deg - alpha, tracked.beta_deg - taught.beta_deg - beta],
            "egi": [egi_alpha - alpha, egi_beta - beta],
            "gamma_raw": raw - gamma, "gamma_compensated": compensated - gamma,
            "signs_plane": [_sign_ok(measured_alpha, alpha), _sign_ok(measured_beta, beta)],
            "signs_egi": [_sign_ok(egi_alpha, alpha), _sign_ok(egi_beta, beta)],
            "frames_first": len(first_sweep), "frames_tracking": len(tracking_sweep),
            "scan_s_first": len(first_sweep) * frame_time, "scan_s_tracking": len(tracking_sweep) * frame_time,
            "plane_ms": plane_ms, "egi_ms": egi_ms, "kernels_used": plane.kernels_used,
        })
        left = (time.monotonic() - started) / index * (len(poses) - index)
        say(f"  pose {index:2d}/{len(poses)} ({alpha:6.2f}, {beta:6.2f}, {gamma:6.1f}): plane "
            f"{rows[-1]['plane'][0]:+.3f} {rows[-1]['plane'][1]:+.3f}, egi {rows[-1]['egi'][0]:+.3f} "
            f"{rows[-1]['egi'][1]:+.3f}, gamma {rows[-1]['gamma_compensated']:+.4f} ({left:.0f} s left)")
    return {"taught": [taught.alpha_deg, taught.beta_deg], "frame_time_s": frame_time, "rows": rows}


def depth_of_field_scan(poses: list[tuple[float, float, float]], seed: int, factors=(1.0, 2.0, 4.0, 8.0),
                        say: Callable[[str], None] = print) -> list[dict]:
    """The plane fit's error as the depth of field grows (a smaller aperture or a longer
    working distance): the beam half-angle divided by each factor, the sweeps scaled to
    the depth of field."""
    rows = []
    for factor in factors:
        lab = Lab(seed)
        lab.world.sem.beam_half_angle /= factor
        depth_of_field = DEPTH_OF_FIELD_UM * factor
        reference_sweep = plan_sweep(0.0, depth_of_field, lab.field_um)
        taught = estimate_tilt(lab.sweep(Pose(), reference_sweep), reference_sweep, lab.pixel_um)
        errors, signs, refused = [], [], 0
        for alpha, beta, gamma in poses:
            measured = estimate_tilt(lab.sweep(Pose(tilt_x_deg=alpha, tilt_y_deg=beta, rotation_deg=gamma),
                                               reference_sweep), reference_sweep, lab.pixel_um)
            if measured.confidence <= 0 or taught.confidence <= 0:
                refused += 1
                continue
            pair = (measured.alpha_deg - taught.alpha_deg, measured.beta_deg - taught.beta_deg)
            errors += [pair[0] - alpha, pair[1] - beta]
            signs += [flag for flag in (_sign_ok(pair[0], alpha), _sign_ok(pair[1], beta)) if flag is not None]
        errors = np.abs(errors) if errors else np.array([math.nan])
        rows.append({"depth_of_field_um": depth_of_field, "mean": float(errors.mean()), "max": float(errors.max()),
                     "sign_errors": int(sum(not flag for flag in signs)), "signs_checked": len(signs),
                     "refused": refused, "poses": len(poses), "frames": len(reference_sweep)})
        say(f"  depth of field {depth_of_field:5.1f} um: |error| mean {rows[-1]['mean']:.3f}, max "
            f"{rows[-1]['max']:.3f} degree, {rows[-1]['sign_errors']} sign errors, {refused} refused")
    return rows


def _sign_ok(measured: float, true: float) -> bool | None:
    """Whether the sign is right, for true angles from 0.5 degree up (None below)."""
    return None if abs(true) < 0.5 else bool(np.sign(measured) == np.sign(true))


def summarize(result: dict) -> dict:
    """:func:`table_one`'s rows summed up per method: |error| mean and max per angle, sign
    errors, frames, scan and compute time."""
    rows = result["rows"]

    def stats(key, index=None):
        values = np.abs([row[key] if index is None else row[key][index] for row in rows])
        return {"mean": float(values.mean()), "max": float(values.max())}

    summary = {}
    for method in ("plane", "plane_tracking", "egi"):
        summary[method] = {"alpha": stats(method, 0), "beta": stats(method, 1)}
    for method in ("plane", "egi"):
        flags = [flag for row in rows for flag in row[f"signs_{method}"] if flag is not None]
        summary[method]["sign_errors"] = int(sum(not flag for flag in flags))
        summary[method]["signs_checked"] = len(flags)
    summary["gamma_raw"] = stats("gamma_raw")
    summary["gamma_compensated"] = stats("gamma_compensated")
    for key in ("frames_first", "frames_tracking", "scan_s_first", "scan_s_tracking", "plane_ms", "egi_ms"):
        summary[key] = {"mean": float(np.mean([row[key] for row in rows])), "max": float(np.max([row[key] for row in rows]))}
    return summary


# -- 5-DOF runs through the whole stack ----------------------------------------

#: A 5-DOF run's settings (the README's Fig. 8 table): tolerances 0.3 px, 0.05 degree of
#: gamma and 0.1 of tilt, at most 4 degrees per turn or tilt command.
RUN_SETTINGS = {"tolerance_px": 0.3, "tolerance_deg": 0.05, "tolerance_tilt_deg": 0.1, "max_iterations": 600,
                "max_turn_deg": 4.0}


def five_dof_runs(initial: list[tuple], folder: Path | None = None, speedup: float = 20.0,
                  say: Callable[[str], None] = print, *, environment: dict[str, str] | None = None,
                  run_settings: dict | None = None) -> list[dict]:
    """5-DOF runs through the whole stack on simulated hardware (started here, on fresh
    loopback ports, its records in ``folder`` or a temporary one; ``environment``: more
    SEMSERVO_* settings, e.g. a sample image): one teach (frames and a focus sweep) at the
    start pose, then per entry of ``initial`` (alpha, beta, gamma in degrees, x, y in um,
    from the taught pose) a displacement and a run servoing x, y, gamma, alpha and beta
    (``run_settings`` over :data:`RUN_SETTINGS`); ``say`` is told once per run. Each result
    carries the run's state, iterations, wall time, the simulator's true final errors
    (``truth``: the stage against the taught pose; ``view_error_px``: how far the content
    at the taught view's centre is from the centre, what the image shows, the tilt
    cradle's pivot included) and the trajectory."""
    from semservo.client import Client
    from semservo.config import connect
    from semservo.launcher import simulated_system
    from semservo.transport import ControlClient

    if folder is None:
        with tempfile.TemporaryDirectory() as temporary:
            return five_dof_runs(initial, Path(temporary), speedup, say, environment=environment,
                                 run_settings=run_settings)
    settings_of_runs = {**RUN_SETTINGS, **(run_settings or {})}
    results = []
    variables = {"SEMSERVO_FAKELAB__PRESET": "tilts", **(environment or {})}
    with simulated_system(folder, speedup=speedup, **variables) as (_launcher, settings):
        lab = Client(f"http://127.0.0.1:{settings.gateway.http_port}", timeout=60)
        fakelab = ControlClient(connect(settings.fakelab.host, settings.fakelab.control_port), timeout_s=10, retries=2)
        try:
            deadline = time.monotonic() + 60
            while lab.status()["latest_frame_seq"] is None and time.monotonic() < deadline:
                time.sleep(0.2)
            reference = lab.teach(frames=4, tilts=True)
            # The taught pose: over the scans of the frames the reference was made from.
            scanned = reference.get("source_interval_s") or (reference.get("detail") or {}).get("source_interval_s")
            taught_pose = _pose(fakelab.request("pose", interval_s=scanned)) if scanned else None
            taught = lab.stage()
            angles, positions = taught["rotation"]["angles_deg"], taught["positions_um"]
            for index, (alpha, beta, gamma, x_um, y_um) in enumerate(initial, 1):
                # From the taught pose (not from where the last run ended): absolute targets.
                lab.move(x_um=positions["x"] + x_um, y_um=positions["y"] + y_um, relative=False)
                targets = {"rotation_deg": gamma, "tilt_x_deg": alpha, "tilt_y_deg": beta}
                lab.rotate(relative=False, **{key: angles[key] + value for key, value in targets.items()})
                time.sleep(25.0 / speedup + 0.5)  # let the stage arrive (4 degrees per second at most)
                started = time.monotonic()
                run = lab.start(dofs=["x", "y", "gamma", "alpha", "beta"], **settings_of_runs)
                record = lab.wait(run["run_id"], timeout=900)
                truth = record.get("truth") or {}
                view = _view_error(fakelab, record, taught_pose)
                results.append({"initial": [alpha, beta, gamma, x_um, y_um], "state": record["state"],
                                "reason": record.get("reason"), "iterations": record["iterations"],
                                "wall_s": time.monotonic() - started, "truth": truth, "view_error_px": view,
                                "tilt_iterations": sum(1 for r in record["trajectory"] if r.get("tilt_action") == "moved"),
                                "trajectory": record["trajectory"]})
                error = truth.get("error_deg", {})
                view_text = f"view {math.hypot(*view):.3f} px" if view else "view unknown"
                say(f"  run {index:2d}/{len(initial)} from ({alpha:+.1f}, {beta:+.1f}, {gamma:+.1f}) deg, ({x_um:+.1f}, "
                    f"{y_um:+.1f}) um: {record['state']} after {record['iterations']} iterations, "
                    f"{results[-1]['wall_s']:.0f} s; true error alpha {error.get('tilt_x_deg', math.nan):+.3f}, beta "
                    f"{error.get('tilt_y_deg', math.nan):+.3f}, gamma {error.get('rotation_deg', math.nan):+.4f} deg, "
                    f"stage {truth.get('error_norm_px', math.nan):.2f} px, {view_text}"
                    + ("" if record["state"] == "converged" else f"\n    reason: {record.get('reason')}"))
        finally:
            fakelab.close()
            lab.close()
    return results


def _pose(answer: dict) -> Pose:
    return Pose(**{key: float(answer[key]) for key in ("x_um", "y_um", "z_um", "rotation_deg", "tilt_x_deg",
                                                        "tilt_y_deg")})


def _view_error(fakelab, record: dict, taught: Pose | None) -> list[float] | None:
    """The image-plane error (px) where the run left the sample: over the scans of the
    frames after its last move (not scanned during it), where the content at the taught
    view's centre is, from the simulator's true poses
    (:func:`semservo.simulation.sem.view_error_px`); None when unknown."""
    from semservo.simulation.sem import view_error_px

    records = record.get("trajectory", [])
    last_move = max((index for index, r in enumerate(records) if r.get("action") == "moved"
                     or r.get("tilt_action") == "moved"), default=-1)
    resting = [r for r in records[last_move + 1:] if r.get("frame_source_interval_s")
               and not str(r.get("action", "")).startswith("held")] or \
        [r for r in records[-1:] if r.get("frame_source_interval_s")]
    if taught is None or not resting or not resting[-1].get("pixel_size_nm"):
        return None
    final = _pose(fakelab.request("pose", interval_s=[resting[0]["frame_source_interval_s"][0],
                                                      resting[-1]["frame_source_interval_s"][1]]))
    return list(view_error_px(final, taught, resting[-1]["pixel_size_nm"] / 1000))


def plot_fig8(run: dict, path: Path) -> None:
    """One 5-DOF run plotted like the paper's Fig. 8: angular velocities and cost per
    iteration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    moved = [r for r in run["trajectory"] if r.get("action") == "moved"]
    iterations = np.arange(len(moved))
    figure, (turning, tilting, costs) = plt.subplots(3, 1, figsize=(7, 8), sharex=True)
    omega_z = [math.degrees(r["velocity"][2]) if len(r.get("velocity", [])) > 2 else 0.0 for r in moved]
    turning.plot(iterations, omega_z, ".-", color="tab:green", label="omega_z (gamma), every fresh frame")
    turning.set_ylabel("deg/s")
    turning.legend()
    sweeps = [(i, r["tilt_velocity"]) for i, r in enumerate(moved) if r.get("tilt_velocity")]
    if sweeps:
        steps, velocity = zip(*sweeps)
        tilting.plot(steps, [math.degrees(v[0]) for v in velocity], "o-", label="omega_x (alpha), at each sweep")
        tilting.plot(steps, [math.degrees(v[1]) for v in velocity], "s-", label="omega_y (beta), at each sweep")
    tilting.set_ylabel("deg/s")
    tilting.legend()
    costs.semilogy(iterations, [max(r.get("cost", 0.0), 1e-6) for r in moved], ".-", label="cost x, y, gamma (eq. 32)")
    tilt_cost = [(i, r["tilt_cost"]) for i, r in enumerate(moved) if r.get("tilt_cost") is not None]
    if tilt_cost:
        costs.semilogy(*zip(*tilt_cost), "o", label="cost alpha, beta (rad^2), at each sweep")
    costs.set_xlabel("iteration")
    costs.set_ylabel("cost")
    costs.legend()
    alpha, beta, gamma = run["initial"][:3]
    figure.suptitle(f"5-DOF run from ({alpha:g}, {beta:g}, {gamma:g}) degrees (cf. paper Fig. 8)")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
