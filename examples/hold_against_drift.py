"""Hold a position against drift for a while: continuous servoing (``hold=True`` keeps
the loop running after convergence), watching the live events, then stop.

Run the system first (`./dev up`), then: `.venv/bin/python examples/hold_against_drift.py 60`
"""

import sys
import time

from semservo.client import Client

duration_s = float(sys.argv[1]) if len(sys.argv) > 1 else 30.0

with Client() as lab:
    lab.teach(frames=4)
    run = lab.start(hold=True, tolerance_px=0.1)
    started = time.monotonic()
    worst = 0.0
    for event in lab.events():
        if event["kind"] == "iteration" and event["data"].get("error_px") is not None:
            worst = max(worst, event["data"]["error_px"])
            print(f"iteration {event['data']['iteration']:4d}: error {event['data']['error_px']:.3f} px")
        if time.monotonic() - started > duration_s:
            break
    lab.stop("hold finished")  # a stop holds the stage, as every stop does ...
    lab.resume()  # ... and the hold being over, the stage may move again (the next script's runs and jogs)
    print(f"held for {duration_s:g} s; largest error seen {worst:.3f} px")
