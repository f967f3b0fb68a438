"""OpenFIBSEM benchmark: semservo's closed loop through fibsem's own calls, judged by the
simulation's truth, beside the fake lab's own loop and fibsem's own alignment.

The microscope is OpenFIBSEM's ``DemoMicroscope`` (fibsem 0.5.3), its frames rendered by
semservo's simulated SEM at its own stage position and beam shift
(:class:`semservo.openfibsem.SimulatedDemoFrames`: the paper's *optimal* condition, x1200
on 512 pixels, 720 ns/px, with the simulated lab's drift and vibration). Each trial,
seeded apart: teach at home (4 frames), jog with ``stable_move`` by a random offset of up
to a quarter of the field per axis, position back; the true error is the pose over the
run's last three scans against the pose over the reference's scans.

Rows, on the same seeds and the same offsets:

* **semservo / OpenFIBSEM, stage**: :class:`semservo.openfibsem.Positioner`, every move by
  ``stable_move`` (``beam_shift_within_um=0``);
* **semservo / OpenFIBSEM, stage then beam shift**: the beam shift once the error is
  within 2 um (``beam_shift_within_um=2``);
* **the fake lab's own loop**: :func:`semservo.reproduce.loop.run_trial` (the simulated
  lab's piezo stage with hysteresis, the same estimator and law, no services);
* **a stage with play** (``--stage-play-um``, default 0.05): each stage move lands within
  that (sigma, per axis) of where it was sent while its encoders read the goal, as a
  mechanical stage does; stage alone, and stage then beam shift;
* **fibsem's own alignment** (the peer a lab uses today): ``beam_shift_alignment_v2``
  with its default method, ``--fibsem-steps`` steps by the stage, then as many by the
  beam shift, from a single reference frame.

    ./dev bench openfibsem                  # 10 trials; --trials N, --out DIR

Writes bench/results/openfibsem.json.
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("FIBSEM_SIM_NO_DELAY", "1")

from fibsem import utils  # noqa: E402
from fibsem.alignment import AlignmentSubsystem, beam_shift_alignment_v2  # noqa: E402
from fibsem.structures import BeamType, ImageSettings  # noqa: E402

from semservo import jsontext  # noqa: E402
from semservo.openfibsem import Positioner, SimulatedDemoFrames  # noqa: E402
from semservo.reproduce.loop import run_trial  # noqa: E402

PIXEL_UM = 212.3 / 1200  # x1200 on 512 pixels (eq. 43)
HFW_UM = PIXEL_UM * 512
DWELL_NS = 720.0
ELECTRON = BeamType.ELECTRON


def say(text: str) -> None:
    print(text, flush=True)


def demo(seed: int, stage_play_um: float = 0.0):
    logging.disable(logging.INFO)  # fibsem's info lines, one per image
    microscope, _ = utils.setup_session(session_path=tempfile.mkdtemp(prefix="semservo-bench-"), manufacturer="Demo",
                                        ip_address="localhost", setup_logging=False)
    return microscope, SimulatedDemoFrames(microscope, seed=seed, stage_play_um=stage_play_um)


def jog(microscope, offset_um: np.ndarray) -> None:
    """Move the content by ``offset_um`` (x right, y down) with fibsem's own call: its
    alignment corrects a content shift (dx, dy) with stable_move(dx, -dy)."""
    microscope.stable_move(dx=-offset_um[0] * 1e-6, dy=offset_um[1] * 1e-6, beam_type=ELECTRON)


def true_error_px(frames: SimulatedDemoFrames, taught: np.ndarray) -> list[float]:
    """Where the run left the content: the pose over its last scan against the taught
    one (as the fake lab's own loop judges it, semservo.reproduce.loop)."""
    return ((frames.true_pose(frames.scans[-1:]) - taught) / PIXEL_UM).tolist()


def semservo_trial(seed: int, offset_um: np.ndarray, beam_within_um: float, stage_play_um: float = 0.0) -> dict:
    microscope, frames = demo(seed, stage_play_um)
    positioner = Positioner(microscope, hfw_um=HFW_UM, dwell_ns=DWELL_NS)
    positioner.teach(frames=4)
    taught = frames.true_pose(frames.scans[-4:])
    jog(microscope, offset_um)
    started = time.perf_counter()
    record = positioner.run(beam_shift_within_um=beam_within_um)
    moved = [set(r["targets"]) for r in record["records"] if r.get("targets")]
    return {"state": record["outcome"]["state"], "reason": record["outcome"]["reason"],
            "iterations": record["iterations"], "wall_s": time.perf_counter() - started,
            "true_error_px": true_error_px(frames, taught),
            "beam_moves": sum(axes == {"beam_x", "beam_y"} for axes in moved),
            "stage_moves": sum(axes == {"x", "y"} for axes in moved)}


def fibsem_trial(seed: int, offset_um: np.ndarray, steps: int) -> dict:
    microscope, frames = demo(seed)
    settings = ImageSettings(resolution=(512, 512), dwell_time=DWELL_NS * 1e-9, hfw=HFW_UM * 1e-6, beam_type=ELECTRON)
    reference = microscope.acquire_image(image_settings=settings)
    taught = frames.true_pose(frames.scans[-1:])
    jog(microscope, offset_um)
    started = time.perf_counter()
    for subsystem in (AlignmentSubsystem.STAGE, AlignmentSubsystem.BEAM_SHIFT):
        for _ in range(steps):
            beam_shift_alignment_v2(microscope, reference, subsystem=subsystem)
    microscope.acquire_image(image_settings=settings)  # where it ended: the frame after the last correction
    return {"state": "done", "iterations": 2 * steps, "wall_s": time.perf_counter() - started,
            "true_error_px": true_error_px(frames, taught)}


def fake_lab_trial(seed: int, offset_um: np.ndarray) -> dict:
    started = time.perf_counter()
    result = run_trial("optimal", "semservo", (float(offset_um[0]), float(offset_um[1])), seed=seed)
    return {"state": result["outcome"], "reason": result["reason"], "iterations": result["iterations"],
            "wall_s": time.perf_counter() - started,
            "true_error_px": (np.array(result["true_error_um"]) / result["pixel_um"]).tolist()}


def summary(trials: list[dict]) -> dict:
    errors = np.abs(np.array([trial["true_error_px"] for trial in trials]))
    ok = [trial for trial in trials if trial["state"] in ("converged", "done")]
    return {"trials": len(trials), "converged": sum(trial["state"] == "converged" for trial in trials),
            "x_mean_px": float(errors[:, 0].mean()), "x_max_px": float(errors[:, 0].max()),
            "y_mean_px": float(errors[:, 1].mean()), "y_max_px": float(errors[:, 1].max()),
            "within_0_1_px": int(np.sum(np.all(errors <= 0.1, axis=1))),
            "iterations_median": float(np.median([trial["iterations"] for trial in ok])) if ok else None,
            "wall_s_median": float(np.median([trial["wall_s"] for trial in trials]))}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--fibsem-steps", type=int, default=3, help="steps of fibsem's alignment, each subsystem")
    parser.add_argument("--stage-play-um", type=float, default=0.05,
                        help="two more rows: a stage that lands within this much (sigma per axis) of where it was "
                             "sent, stage alone and stage then beam shift (0: leave them out)")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(29)
    field_um = 512 * PIXEL_UM
    cases = [(trial + 1, rng.uniform(-field_um / 4, field_um / 4, 2)) for trial in range(args.trials)]
    rows = {"semservo / OpenFIBSEM, stage": lambda seed, offset: semservo_trial(seed, offset, 0.0),
            "semservo / OpenFIBSEM, stage then beam shift": lambda seed, offset: semservo_trial(seed, offset, 2.0),
            "fake lab's own loop (simulated piezo stage)": fake_lab_trial,
            f"fibsem's alignment ({args.fibsem_steps} stage + {args.fibsem_steps} beam steps)":
                lambda seed, offset: fibsem_trial(seed, offset, args.fibsem_steps)}
    if args.stage_play_um > 0:
        play = args.stage_play_um
        rows[f"semservo / OpenFIBSEM, stage with {play:g} um of play"] = \
            lambda seed, offset: semservo_trial(seed, offset, 0.0, play)
        rows[f"semservo / OpenFIBSEM, stage with {play:g} um of play, then beam shift"] = \
            lambda seed, offset: semservo_trial(seed, offset, 2.0, play)
    results = {}
    for name, trial in rows.items():
        runs = []
        for seed, offset in cases:
            runs.append({"seed": seed, "offset_um": offset.tolist(), **trial(seed, offset)})
            error = runs[-1]["true_error_px"]
            say(f"  {name} trial {seed}/{args.trials}: {runs[-1]['state']} in {runs[-1]['iterations']} iterations, "
                f"true error {error[0]:+.3f}, {error[1]:+.3f} px")
        results[name] = {"summary": summary(runs), "trials": runs}
    say("")
    say(f"OpenFIBSEM closed loop, {args.trials} trials (jogs up to a quarter field per axis, x1200, 720 ns/px); "
        "true error from the simulation, px")
    say("| loop | converged | within 0.1 px (x and y) | x mean / max | y mean / max | iterations (median) |")
    say("| --- | --- | --- | --- | --- | --- |")
    for name, result in results.items():
        row = result["summary"]
        converged = f"{row['converged']}/{row['trials']}" if not name.startswith("fibsem") else "n/a (fixed steps)"
        say(f"| {name} | {converged} | {row['within_0_1_px']}/{row['trials']} | {row['x_mean_px']:.3f} / "
            f"{row['x_max_px']:.3f} | {row['y_mean_px']:.3f} / {row['y_max_px']:.3f} | {row['iterations_median']:g} |")
    (args.out / "openfibsem.json").write_text(jsontext.dumps({"cases": [[s, o.tolist()] for s, o in cases],
                                                              "results": results}, indent=1))
    say(f"\nwrote {args.out / 'openfibsem.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
