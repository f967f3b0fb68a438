"""Simulated lab benchmark: render time per 512 x 512 frame for every preset (one core),
frame time at each scan speed, SNR by dwell, and the emulated piezo's hysteresis.
Target (issue 4): a 512 x 512 frame rendered in at most 25 ms on one core.

    ./dev bench simulation
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sys  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from semservo.estimation import estimate_snr_db  # noqa: E402
from semservo.simulation.piezo import PiezoAxis  # noqa: E402
from semservo.simulation.sem import SEM, Pose, ScanSettings  # noqa: E402
from semservo.simulation.world import PRESETS  # noqa: E402

cv2.setNumThreads(1)


def main(argv: list[str] | None = None) -> int:
    import argparse

    argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter).parse_args(argv)
    print(f"{'preset':24s} {'scene':12s} {'xG':>6s} {'ns/px':>6s} {'frame s':>8s} {'render ms':>10s} "
          f"{'moving ms':>10s} {'SNR dB':>7s}")
    worst = 0.0
    for name, preset in PRESETS.items():
        sem = SEM(preset.scene)
        settings = ScanSettings(dwell_ns=preset.dwell_ns, magnification=preset.magnification)
        rng = np.random.default_rng(0)
        still_poses = [Pose()] * 512
        sem.render(settings, still_poses, still_poses, rng)  # builds the blur stack once
        start = [Pose(x_um=2.0 * r / 512) for r in range(512)]
        end = [Pose(x_um=2.0 * (r + 1) / 512) for r in range(512)]
        timings = {"still": [], "moving": []}
        for _ in range(15):
            for kind, (first, last) in (("still", (still_poses, still_poses)), ("moving", (start, end))):
                began = time.perf_counter()
                sem.render(settings, first, last, rng)
                timings[kind].append(time.perf_counter() - began)
        still_ms = float(np.median(timings["still"]) * 1e3)
        moving_ms = float(np.median(timings["moving"]) * 1e3)
        worst = max(worst, still_ms, moving_ms)
        snr = estimate_snr_db(sem.render(settings, still_poses, still_poses, rng))
        print(f"{name:24s} {preset.scene:12s} {preset.magnification:6.0f} {preset.dwell_ns:6.0f} "
              f"{settings.frame_time_s:8.3f} {still_ms:10.1f} {moving_ms:10.1f} {snr:7.1f}", flush=True)
    print(f"slowest render: {worst:.1f} ms per 512 x 512 frame (target <= 25 ms): {'met' if worst <= 25 else 'NOT met'}")
    print("\nEmulated TRITOR hysteresis (loop width as % of the move)")
    for axis_name in "xy":
        widths = []
        for low, high in ((-19, 96), (20, 60), (35, 45), (38, 40)):
            axis = PiezoAxis(axis_name)
            volts = np.linspace(low, high, 200)
            for _ in range(2):
                rising = np.array([axis.hysteresis.apply(v) for v in volts])
                falling = np.array([axis.hysteresis.apply(v) for v in volts[::-1]])[::-1]
            widths.append(f"{high - low:>4.0f} V: {100 * (falling - rising).max() / (rising.max() - rising.min()):5.1f} %")
        print(f"    {axis_name}: " + "   ".join(widths))
    return 0


if __name__ == "__main__":
    sys.exit(main())
