"""Time to target, the position law beside the paper's (issue #28).

``./dev bench time_to_target``: time to target, the position law beside the paper's
(issue #28), on the simulated lab in process (a continuously scanning SEM, the piezo
stage with hysteresis, creep, drift and vibration; :func:`semservo.reproduce.loop.run_timed_trial`).

Per preset (the seven positioning presets) and offset (5, 15, 30 % of the field and half a
pixel), N trials each for both laws: fresh frames used, frames scanned in all, simulated
seconds at the preset's frame rate, the true final error, converged of N; the position law
also with the stage's model unknown (a linear model from the nominal stroke) and with
another stage's (+-15 %), the paper's law also without calibration; the photometric
baseline's time to target. The same experiment as ``semservo reproduce --only
time_to_target`` (this script runs trials in parallel), written into the reproduction
report (``docs/reproduction`` by default) with its plot ``time_to_target.png``. Results
are kept per trial: an interrupted run resumes where it stopped (``--fresh`` starts over).

    nice -n 10 ./dev bench time_to_target            # the full run, two processes
    ./dev bench time_to_target --quick               # two presets, two trials: a few minutes
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from semservo import jsontext
from semservo import reproduce
from semservo.reproduce import loop, report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="optimal and high-magnification, 2 trials per cell")
    parser.add_argument("--trials", type=int, default=None, help="trials per cell (default 10; quick 2)")
    parser.add_argument("--presets", nargs="+", choices=reproduce.FIGURE_CASES, default=None)
    parser.add_argument("--models", nargs="+", choices=loop.STAGE_MODELS, default=None,
                        help="the stage's displacement models (default: all four)")
    parser.add_argument("--no-baseline", action="store_true", help="skip the photometric baseline")
    parser.add_argument("--workers", type=int, default=2, help="processes (default 2: the machine is shared)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "docs" / "reproduction",
                        help="where the report goes (default docs/reproduction)")
    parser.add_argument("--fresh", action="store_true", help="forget the trials kept from an earlier run")
    args = parser.parse_args(argv)

    results = args.out / "results"
    results.mkdir(parents=True, exist_ok=True)
    checkpoint = results / f"time_to_target{'.quick' if args.quick else ''}.partial.jsonl"
    if args.fresh and checkpoint.is_file():
        checkpoint.unlink()
    started = time.monotonic()
    result = reproduce.experiment_time_to_target(
        args.quick, lambda total: reproduce.Progress("time", total), checkpoint=checkpoint, workers=args.workers,
        trials=args.trials, cases=args.presets, models=args.models, baseline=not args.no_baseline)
    result.update(quick=args.quick, seconds=round(time.monotonic() - started, 1),
                  finished_at=time.strftime("%Y-%m-%d %H:%M:%S"))
    (results / "time_to_target.json").write_text(jsontext.dumps(result))
    print("\n".join(report.time_to_target_headline_lines(result)))
    print()
    print("\n".join(report.time_to_target_targets(result)))
    report.write(args.out, say=print)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
