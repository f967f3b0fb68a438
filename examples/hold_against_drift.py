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
    # First the status as it is ("hello": a stop before the stream opened is seen there),
    # then the iterations while servoing and a status at every change of state; None after
    # a quiet second (no events come after a run ends, and a lost one never comes).
    for event in lab.events(quiet_s=1.0):
        if event is None:
            status = lab.status()
            event = {"kind": "status", "data": {"run_id": status.run_id, "state": status.state,
                                                "reason": status.reason}}
        data = event["data"]
        if event["kind"] == "iteration" and data.get("error_px") is not None:
            worst = max(worst, data["error_px"])
            # One event per fresh frame; the iteration counts moves, so a hold that needs
            # none repeats it: the frame and what the run did tell the lines apart.
            print(f"frame {data['seq']:6d} (move {data['iteration']:3d}): error {data['error_px']:.3f} px, "
                  f"{data['action']}")
        if (event["kind"] in ("hello", "status") and data.get("run_id") == run.run_id
                and data.get("state") in FINISHED):
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
