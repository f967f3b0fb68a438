"""CPU benchmark: each service's share of a core, idle and during a run.

Starts the whole system as ``semservo up`` does (simulated hardware at its real speed:
the optimal preset's 2.2 frames per second, the image server's default rate, fresh
loopback ports), lets it settle, then reads every process's CPU time from
``/proc/<pid>/stat`` over ``--seconds`` twice: idle (nothing taught, no run) and while a
run holds a taught position against drift (``hold=True``). Prints a table, percent of
one core per service, and writes ``bench/results/cpu.json``.

    ./dev bench cpu                 # or: python bench/cpu.py --seconds 30
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from semservo import jsontext
from semservo.client import Client
from semservo.launcher import simulated_system

OUT = Path(__file__).parent / "results"
TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (its threads included)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def shares(pids: dict[str, int], seconds: float) -> dict[str, float]:
    """Percent of one core each process used over ``seconds`` of wall time."""
    before = {name: cpu_seconds(pid) for name, pid in pids.items()}
    started = time.monotonic()
    time.sleep(seconds)
    elapsed = time.monotonic() - started
    return {name: 100 * (cpu_seconds(pid) - before[name]) / elapsed for name, pid in pids.items()}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="each measurement's length (default 30)")
    parser.add_argument("--settle", type=float, default=10.0, help="seconds to let the system settle first")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder, \
            simulated_system(Path(folder), speedup=1.0, fps=10.0) as (launcher, settings):
        pids = {name: child.process.pid for name, child in launcher.children.items()}
        time.sleep(args.settle)
        idle = shares(pids, args.seconds)
        with Client(f"http://127.0.0.1:{settings.gateway.http_port}", timeout=30) as lab:
            lab.teach(frames=2)
            run = lab.start(hold=True, tolerance_px=0.1)
            time.sleep(2.0)
            running = shares(pids, args.seconds)
            lab.stop("cpu benchmark over")
            state = lab.wait(run.run_id, timeout=15).state
    rows = [(name, idle[name], running[name]) for name in pids]
    print(f"CPU, percent of one core, over {args.seconds:g} s each (2.2 frames/s, the optimal preset, real time):")
    print(f"{'service':<12} {'idle':>7} {'run':>7}")
    for name, at_rest, busy in rows:
        print(f"{name:<12} {at_rest:6.1f}% {busy:6.1f}%")
    print(f"{'all':<12} {sum(idle.values()):6.1f}% {sum(running.values()):6.1f}%   (the run ended {state})")
    OUT.mkdir(exist_ok=True)
    (OUT / "cpu.json").write_text(jsontext.dumps({"seconds": args.seconds, "idle": idle, "run": running}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
