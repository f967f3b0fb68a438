"""Fault campaign benchmark: break the running system one fault at a time and print what
held (semservo.faults; the same cases tests/faults/ asserts).

Starts the whole system on simulated hardware as ``semservo up --restart`` does (the lab
at ``--speedup`` x, loopback only), then for each case: kill a service with SIGKILL
mid-run (estimator, image server, controller, stage, fake lab, gateway), pull the serial
cable, flood the amplifier's port with garbage, flood the frames tenfold, freeze the
frame source. Prints the table (time to hold, outcome, records complete, next run
converged, amplifier within its limits) and writes it with the details as JSON.

    ./dev bench faults            # or: python bench/faults.py --only "kill controller"
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

from semservo import jsontext
from semservo.client import Client
from semservo.config import Settings
from semservo.faults import Campaign, table
from semservo.launcher import Launcher

OUT = Path(__file__).parent / "results"
SERVICES = ("estimator", "imageserver", "controller", "stage", "fakelab", "gateway")


def cases(campaign: Campaign) -> dict:
    run = {f"kill {name}": (lambda name=name: campaign.kill_mid_run(name)) for name in SERVICES}
    run["serial cable pulled"] = campaign.pulled_serial_link
    run["garbage on the amplifier"] = campaign.garbage_on_the_amplifier
    run["10x frame flood"] = campaign.frame_flood
    run["frozen frame source"] = campaign.frozen_frame_source
    return run


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--speedup", type=float, default=20.0, help="simulated lab speed (default 20x)")
    parser.add_argument("--only", action="append", help="run only this case (repeatable), e.g. 'kill stage'")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="semservo-faults-"))
    os.environ.update({
        "SEMSERVO_FAKELAB__SPEEDUP": str(args.speedup), "SEMSERVO_STAGE__MAX_RATE_V_PER_S": str(200 * args.speedup),
        "SEMSERVO_IMAGESERVER__FPS": "30", "SEMSERVO_CONTROLLER__RUNS_DIR": str(work / "runs"),
        "SEMSERVO_GATEWAY__DATABASE": str(work / "runs" / "semservo.sqlite"), "SEMSERVO_STAGE__STATE_DIR": str(work),
    })
    settings = Settings()
    log = (work / "services.log").open("w")
    launcher = Launcher(settings, restart=True, max_restarts=20, out=log)
    print(f"starting the system on simulated hardware (x{args.speedup:g}); service logs: {work / 'services.log'}",
          flush=True)
    launcher.start(timeout_s=120)
    client = Client(f"http://127.0.0.1:{settings.gateway.http_port}", timeout=15)
    results = []
    try:
        with Campaign(launcher, client, settings, say=lambda text: log.write(text + "\n")) as campaign:
            chosen = cases(campaign)
            unknown = set(args.only or ()) - set(chosen)
            if unknown:
                parser.error(f"unknown case(s) {sorted(unknown)}; cases: {', '.join(chosen)}")
            names = args.only or list(chosen)
            for index, name in enumerate(names, 1):
                print(f"[{index}/{len(names)}] {name} ...", end=" ", flush=True)
                started = time.monotonic()
                result = chosen[name]()
                results.append(result)
                print(f"{'ok' if result.passed else 'FAILED'} in {time.monotonic() - started:.0f} s", flush=True)
    finally:
        client.close()
        launcher.stop()
        log.close()
    print()
    print(table(results))
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "faults.json"
    path.write_text(jsontext.dumps({"speedup": args.speedup, "cases": [asdict(result) for result in results]}, indent=1))
    print(f"\nwritten: {path}")
    return 0 if all(result.passed for result in results) else 1


if __name__ == "__main__":
    sys.exit(main())
