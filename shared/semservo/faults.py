"""The fault campaign: break a running semservo on simulated hardware, one fault at a
time, and check what must hold whatever breaks.

For each case (a service killed with SIGKILL mid-run and restarted by the launcher, the
serial cable pulled, garbage on the amplifier's port, a frame flood, a frozen frame
source):

* **held**: the stage writes no voltage later than the watchdog time after the fault
  (``time_to_hold_s``), or is ``held`` by then when its controller died; and the
  amplifier's outputs never leave the soft limits (sampled from the fake lab all along);
* **outcome**: the run ends with a clear outcome and reason, within seconds;
* **record**: ``GET /runs/{id}`` is complete: outcome, iterations, the stage's command
  log, and the simulator's truth (or the reason it cannot be known);
* **next run**: a new run converges.

``tests/faults/`` asserts each case; ``bench/faults.py`` prints the table. Both drive a
:class:`semservo.launcher.Launcher` started with ``restart=True`` (as ``semservo up
--restart``) through the REST API (:mod:`semservo.client`) and each service's control
socket, as a reliability engineer would.
"""

from __future__ import annotations

import contextlib
import os
import random
import signal
import socket
import threading
import time
from dataclasses import dataclass, field

from semservo.client import Client, SemservoError
from semservo.config import Settings, connect
from semservo.launcher import Launcher
from semservo.transport import CommandError, ControlClient, ServiceUnavailable

FINISHED = ("converged", "failed", "stopped")


@dataclass
class CaseResult:
    """One row of the campaign's table."""

    case: str
    time_to_hold_s: float | None = None  # fault -> last voltage written (or -> 'held' when the controller died)
    outcome: str = ""  # the run's state: reason
    time_to_outcome_s: float | None = None
    records_complete: bool = False
    missing: list[str] = field(default_factory=list)  # what the record lacks
    next_run_converged: bool = False
    within_limits: bool = True  # every sampled amplifier output within the soft limits
    stage_after_restart: str | None = None  # the stage's state when it came back (a killed stage)
    notes: list[str] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return self.records_complete and self.next_run_converged and self.within_limits and bool(self.outcome)


class VoltageWatch:
    """Samples the amplifier's outputs from the fake lab (its true voltages) every 50 ms
    in a thread, and counts samples outside the soft limits."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.low, self.high = settings.stage.voltage_min, settings.stage.voltage_max
        self.samples = 0
        self.outside: list[tuple[float, list[float]]] = []
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._watch, name="voltage-watch", daemon=True)

    def __enter__(self) -> "VoltageWatch":
        self.thread.start()
        return self

    def __exit__(self, *_exc) -> None:
        self._stop.set()
        self.thread.join(timeout=5)

    def _watch(self) -> None:
        fakelab = ControlClient(connect(self.settings.fakelab.host, self.settings.fakelab.control_port),
                                timeout_s=0.3, retries=1)
        try:
            while not self._stop.wait(0.05):
                try:
                    voltages = fakelab.request("pose")["voltages"]
                except (ServiceUnavailable, CommandError):
                    continue  # the fake lab itself may be the fault
                self.samples += 1
                channels = list(self.settings.stage.axes.values())
                if any(not self.low - 1e-6 <= voltages[channel] <= self.high + 1e-6 for channel in channels):
                    self.outside.append((time.time(), voltages))
        finally:
            fakelab.close()


class Campaign:
    """Faults against one running stack (started by ``launcher``, reached through
    ``client``). The launcher is supervised in a thread, so killed services come back."""

    def __init__(self, launcher: Launcher, client: Client, settings: Settings, *, say=print):
        self.launcher = launcher
        self.client = client
        self.settings = settings
        self.say = say
        self._supervising = threading.Event()
        self._supervisor: threading.Thread | None = None

    # -- plumbing -----------------------------------------------------------------------
    def __enter__(self) -> "Campaign":
        self._supervising.set()
        self._supervisor = threading.Thread(target=self._supervise, name="supervise", daemon=True)
        self._supervisor.start()
        return self

    def __exit__(self, *_exc) -> None:
        self._supervising.clear()
        if self._supervisor is not None:
            self._supervisor.join(timeout=5)

    def _supervise(self) -> None:
        while self._supervising.is_set():
            self.launcher.supervise()
            time.sleep(0.1)

    def control(self, name: str, timeout_s: float = 1.0) -> ControlClient:
        endpoints = {"fakelab": self.settings.fakelab, "imageserver": self.settings.imageserver,
                     "estimator": self.settings.estimator, "stage": self.settings.stage,
                     "controller": self.settings.controller, "gateway": self.settings.gateway}
        config = endpoints[name]
        return ControlClient(connect(config.host, config.control_port), timeout_s=timeout_s, retries=1)

    def ask(self, name: str, command: str, **args):
        client = self.control(name)
        try:
            return client.request(command, **args)
        finally:
            client.close()

    def wait_for(self, predicate, timeout_s: float, what: str):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                value = predicate()
            except (SemservoError, ServiceUnavailable, CommandError):
                value = None
            if value:
                return value
            time.sleep(0.1)
        raise TimeoutError(f"timed out after {timeout_s:g} s waiting for {what}")

    def healthy(self, name: str) -> bool:
        try:
            health = self.ask(name, "health")
        except (ServiceUnavailable, CommandError):
            return False
        child = self.launcher.children[name]
        return health["pid"] == child.process.pid and health["state"] in ("running", "idle")

    def all_healthy(self, timeout_s: float = 60) -> None:
        """Every service back (its own process), the serial link up, none degraded, and
        frames scanned since (a teach must not take a frame of a world that restarted)."""
        for name in self.launcher.children:
            self.wait_for(lambda name=name: self.healthy(name), timeout_s, f"{name} healthy")
        self.wait_for(lambda: self.client.status()["stage"]["link"] == "connected", timeout_s, "the serial link")
        self.wait_for(lambda: not self.client.status()["degraded"], timeout_s, "no service degraded")
        seq = self.wait_for(lambda: self.client.status()["latest_frame_seq"], timeout_s, "frames")
        self.wait_for(lambda: (self.client.status()["latest_frame_seq"] or 0) >= seq + 2, timeout_s, "fresh frames")

    # -- runs ---------------------------------------------------------------------------
    def displaced_run(self, *, hold: bool, dx_um: float = 6.0, dy_um: float = -4.0, **settings) -> str:
        """Teach where the stage stands, jog away, start a run back."""
        self.all_healthy()
        self.wait_for(lambda: self.client.status()["latest_frame_seq"] is not None, 30, "frames")
        self.client.teach(frames=1)
        self.wait_for(lambda: self._jog(dx_um, dy_um), 15, "the jog")
        return self.client.start(resume=True, hold=hold, **settings)["run_id"]

    def _jog(self, dx_um: float, dy_um: float) -> bool:
        try:
            self.client.move(x_um=dx_um, y_um=dy_um)
        except SemservoError as error:
            if error.code == "rate_limit":  # right after a run's last move: again in a moment
                return False
            if error.code in ("held", "stopped"):  # left so by the last case: the operator resumes
                self.client.http.post("/stage/resume")
                return False
            raise
        return True

    def iterations(self, run_id: str) -> int:
        status = self.client.status()
        return status["iteration"] if status["run_id"] == run_id else 0

    def wait_finished(self, run_id: str, timeout_s: float = 60) -> dict:
        """The run's record once it ended (the gateway may be the fault: it is asked
        again until it answers)."""

        def finished():
            run = self.client.run(run_id)
            return run if run["state"] in FINISHED and not (run.get("outcome") or {}).get("provisional") else None

        return self.wait_for(finished, timeout_s, f"run {run_id} to end")

    def settled(self, run_id: str, timeout_s: float = 20) -> dict:
        """The run's record once the gateway completed it (the stage's log or the truth
        may come a few seconds after a restart), or as it is after ``timeout_s``."""
        pending = ("provisional", "stage_log_error", "truth_pending")

        def complete():
            run = self.client.run(run_id)
            return run if not any((run.get("outcome") or {}).get(key) for key in pending) else None

        try:
            return self.wait_for(complete, timeout_s, f"run {run_id}'s record to be complete")
        except TimeoutError:
            return self.client.run(run_id)

    def missing(self, run: dict, *, truth: bool) -> list[str]:
        """What a complete record has and this one lacks."""
        gaps = []
        outcome = run.get("outcome") or {}
        if run["state"] not in FINISHED:
            gaps.append(f"state is {run['state']}")
        if not outcome.get("reason"):
            gaps.append("no outcome reason")
        if not run.get("trajectory"):
            gaps.append("no iterations")
        if not run.get("stage_commands"):
            gaps.append("no stage command log")
        if outcome.get("stage_log_error"):
            gaps.append(f"stage log: {outcome['stage_log_error']}")
        if truth and run.get("truth") is None:
            gaps.append(f"no truth ({outcome.get('truth_unavailable', 'no reason given')})")
        if not truth and run.get("truth") is None and not outcome.get("truth_unavailable"):
            gaps.append("no truth and no reason why")
        return gaps

    def next_run_converges(self) -> bool:
        run_id = self.displaced_run(hold=False, dx_um=4.0, dy_um=3.0, tolerance_px=0.15)
        return self.wait_finished(run_id, timeout_s=120)["state"] == "converged"

    def last_write_after(self, since_ns: int) -> float | None:
        """Seconds from ``since_ns`` to the stage's last voltage command (None: none)."""
        entries = self.wait_for(lambda: self.ask("stage", "log", since_ns=since_ns), 30, "the stage's log")["entries"]
        writes = [entry["time_ns"] for entry in entries if entry["direction"] == "sent" and
                  entry["text"].startswith(("set,", "setall,"))]
        return (max(writes) - since_ns) / 1e9 if writes else 0.0

    # -- the cases ----------------------------------------------------------------------
    def moving_run(self) -> tuple[str, int]:
        """A run holding against drift, three iterations in: (its id, its iteration)."""
        run_id = self.displaced_run(hold=True, tolerance_px=0.1)
        self.wait_for(lambda: self.iterations(run_id) >= 3, 60, "three iterations")
        return run_id, self.iterations(run_id)

    def conclude(self, result: CaseResult, run: dict, *, fault_ns: int | None, truth: bool = True,
                 next_run: bool = True) -> CaseResult:
        """What every case checks once its run ended: the outcome and how long after the
        fault, the last voltage written after it, the record, and the next run."""
        if fault_ns is not None:
            result.time_to_outcome_s = ((run.get("finished_at_ns") or time.time_ns()) - fault_ns) / 1e9
            if result.time_to_hold_s is None:
                result.time_to_hold_s = self.last_write_after(fault_ns)
        result.outcome = f"{run['state']}: {run['reason']}"
        self.all_healthy()
        result.missing = self.missing(self.settled(run["id"]), truth=truth)
        result.records_complete = not result.missing
        result.next_run_converged = next_run and self.next_run_converges()
        return result

    def kill_mid_run(self, name: str) -> CaseResult:
        """SIGKILL one service while a run (holding against drift) is moving the stage."""
        result = CaseResult(f"kill {name}")
        with VoltageWatch(self.settings) as watch:
            run_id, at_kill = self.moving_run()
            killed_ns = time.time_ns()
            self.launcher.children[name].process.kill()
            self.say(f"  killed {name} (pid {self.launcher.children[name].process.pid}) in run {run_id}")
            if name == "controller":
                # Its stage's watchdog holds the stage.
                state = self.wait_for(lambda: self.ask("stage", "state")["state"] == "held" and time.time_ns(),
                                      self.settings.controller.watchdog_s + 5, "the stage to hold")
                result.time_to_hold_s = (state - killed_ns) / 1e9

            def ended_or_going_on():
                run = self.client.run(run_id)
                if run["state"] in FINISHED and not (run.get("outcome") or {}).get("provisional"):
                    return "ended"
                if self.healthy(name) and self.iterations(run_id) > at_kill + 2:
                    return "going on"
                return None

            if self.wait_for(ended_or_going_on, 60, f"run {run_id} to end or go on") == "going on":
                # The service came back fast enough for the run not to notice (the image
                # server, the gateway): it is stopped here, and held from the stop on.
                result.notes.append(f"the run went on once {name} was back")
                killed_ns = time.time_ns()
                self.client.stop(f"fault campaign: the run survived a killed {name}")
            run = self.wait_finished(run_id)
            if name == "stage":
                self.wait_for(lambda: self.healthy("stage"), 60, "the stage back")
                result.stage_after_restart = self.ask("stage", "state")["state"]
            self.conclude(result, run, fault_ns=killed_ns, truth=name != "fakelab")
        result.within_limits = not watch.outside
        result.notes.append(f"{watch.samples} voltage samples")
        return result

    def pulled_serial_link(self) -> CaseResult:
        result = CaseResult("serial cable pulled mid-run")
        with VoltageWatch(self.settings) as watch:
            run_id, _ = self.moving_run()
            pulled_ns = time.time_ns()
            self.ask("fakelab", "serial_link", plugged=False)
            try:
                run = self.wait_finished(run_id)
            finally:
                self.ask("fakelab", "serial_link", plugged=True)
            self.conclude(result, run, fault_ns=pulled_ns)
        result.within_limits = not watch.outside
        return result

    def garbage_on_the_amplifier(self, megabytes: float = 1.0) -> CaseResult:
        """A second client floods the amplifier's TCP port with garbage during a run;
        the run must converge all the same (the stage service's own link is untouched)."""
        result = CaseResult(f"{megabytes:g} MB of garbage on the amplifier's port")
        with VoltageWatch(self.settings) as watch:
            run_id = self.displaced_run(hold=False, tolerance_px=0.15)
            sent = _flood(self.settings.fakelab.host, self.settings.fakelab.serial_tcp_port, int(megabytes * 2**20))
            result.notes.append(f"{sent} bytes sent")
            run = self.wait_finished(run_id, timeout_s=120)
            self.conclude(result, run, fault_ns=None, next_run=run["state"] == "converged")
        result.within_limits = not watch.outside
        return result

    def frame_flood(self, factor: float = 10.0) -> CaseResult:
        """The image server asked for ``factor`` x its frame rate: the estimator keeps to
        the newest frame, and the run converges."""
        result = CaseResult(f"{factor:g}x frame flood")
        before = self.ask("imageserver", "info")["fps"]
        try:
            self.ask("imageserver", "set_fps", fps=before * factor)
            with VoltageWatch(self.settings) as watch:
                run_id = self.displaced_run(hold=False, tolerance_px=0.15)
                run = self.wait_finished(run_id, timeout_s=120)
                self.conclude(result, run, fault_ns=None, next_run=False)
            result.next_run_converged = run["state"] == "converged"  # the run under the flood is the test
            stale = self.ask("estimator", "health")["counters"].get("frames_stale", 0)
            result.notes.append(f"estimator skipped {stale} stale frames")
        finally:
            self.ask("imageserver", "set_fps", fps=before)
        result.within_limits = not watch.outside
        return result

    def frozen_frame_source(self, frozen_s: float = 8.0) -> CaseResult:
        """The SEM hangs (the fake lab is paused with SIGSTOP) mid-run: the image server
        says it is degraded, the run fails with the reason, and all recovers after."""
        result = CaseResult("frame source frozen mid-run")
        fakelab = self.launcher.children["fakelab"].process
        with VoltageWatch(self.settings) as watch:
            run_id, _ = self.moving_run()
            frozen_ns = time.time_ns()
            os.kill(fakelab.pid, signal.SIGSTOP)
            try:
                self.wait_for(lambda: "imageserver" in self.client.status()["degraded"], 20,
                              "the image server to report the frozen source")
                result.notes.append(f"imageserver degraded after {(time.time_ns() - frozen_ns) / 1e9:.1f} s")
                run = self.wait_finished(run_id)
                time.sleep(max(0.0, frozen_s - (time.time_ns() - frozen_ns) / 1e9))
            finally:
                os.kill(fakelab.pid, signal.SIGCONT)
            self.conclude(result, run, fault_ns=frozen_ns)
        result.within_limits = not watch.outside
        return result


def _flood(host: str, port: int, size: int) -> int:
    """Random bytes (and NaN, inf and out-of-range commands) to the amplifier's TCP port."""
    generator = random.Random(13)
    poison = [b"set,0,nan\r", b"set,1,inf\r", b"set,0,1e308\r", b"setall,-1e9,1e9,nan\r", b"cloop,0,7\r"]
    sent = 0
    with socket.create_connection((host, port), timeout=5) as connection:
        connection.settimeout(0.5)
        while sent < size:
            chunk = generator.randbytes(4096) + generator.choice(poison)
            connection.sendall(chunk)
            sent += len(chunk)
            # Read the error replies, so the emulator is never blocked on us; none yet: send on.
            with contextlib.suppress(TimeoutError, socket.timeout):
                connection.recv(65536)
    return sent


def table(results: list[CaseResult]) -> str:
    """The campaign as a Markdown table."""
    rows = ["| case | time to hold | outcome | time to outcome | records complete | next run converged | "
            "within limits |", "|---|---|---|---|---|---|---|"]
    for result in results:
        hold = "—" if result.time_to_hold_s is None else f"{result.time_to_hold_s:.2f} s"
        outcome_time = "—" if result.time_to_outcome_s is None else f"{result.time_to_outcome_s:.1f} s"
        complete = "yes" if result.records_complete else f"no: {'; '.join(result.missing)}"
        rows.append(f"| {result.case} | {hold} | {result.outcome[:110]} | {outcome_time} | {complete} | "
                    f"{'yes' if result.next_run_converged else 'no'} | {'yes' if result.within_limits else 'NO'} |")
    return "\n".join(rows)
