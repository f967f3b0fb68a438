"""Hold a position against drift for a while: continuous servoing (``hold=True`` keeps
the loop running after convergence), watching the live events, then stop.

Run the system first (`./dev up`), then: `.venv/bin/python examples/hold_against_drift.py 60`

If the run ends before the hold is over (an operator's stop, a fault), the script says
why and leaves the stage as that left it: it resumes only the stop it made itself.
"""

import sys
import time

from semservo.client import FINISHED, Client

duration_s = float(sys.argv[1]) if len(sys.argv) > 1 else 30.0

with Client() as lab:
    lab.teach(frames=4)
    run = lab.start(hold=True, tolerance_px=0.1)
    started = time.monotonic()
    worst = 0.0
    ended = None  # the run's own end, if it came first
    for event in lab.events():  # iterations while servoing; a status at every change of state
        data = event["data"]
        if event["kind"] == "iteration" and data.get("error_px") is not None:
            worst = max(worst, data["error_px"])
            print(f"iteration {data['iteration']:4d}: error {data['error_px']:.3f} px")
        if event["kind"] == "status" and event["run_id"] == run.run_id and data.get("state") in FINISHED:
            ended = f"{data['state']}: {data.get('reason') or 'no reason given'}"
            break
        if time.monotonic() - started > duration_s:
            break
    if ended is not None:
        print(f"the run ended after {time.monotonic() - started:.0f} s, before the hold was over ({ended}); "
              f"largest error seen {worst:.3f} px")
        sys.exit(1)
    lab.stop("hold finished")  # a stop holds the stage, as every stop does ...
    lab.resume()  # ... and this hold being over, the stage may move again (the next script's runs and jogs)
    print(f"held for {duration_s:g} s; largest error seen {worst:.3f} px")
