"""The stage service's core: one stage driver (by default the NV 40/3 on its serial
link), and every safety rule, whatever the caller asks and whatever the driver. No
sockets here (the service's main wires them); the link is real (pyserial, through
:class:`semservo.nv40_driver.NV403Driver`, or any :class:`semservo.instruments.StageDriver`).

Safety, in the order a move is checked:

1. the stage must not be stopped (``stop``) or held (the watchdog tripped);
2. the serial link must be up: nothing is pretended to have happened;
3. each target displacement within the travel limits (um, the model's estimate);
4. each voltage within the soft limits (and the device's own, read at connect);
5. each voltage step within ``max_step_v``, and the rate since that channel's last
   write within ``max_rate_v_per_s``.

A move that breaks any rule is refused as a whole with the reason (:class:`Refused`),
never clipped. The rotation-and-tilt stage, when the lab has one (``rotate``), follows
the same rules where they apply: state, owner, finite, within its travel, at most
``max_turn_deg`` per command. The watchdog: a run's controller arms it; if the controller then goes
silent for ``timeout_s`` (no move, no heartbeat) the stage holds where it is and
refuses moves until it is armed again or resumed. While armed, the stage moves for its
owner only: a jog from anyone else is refused (``owned``).

What must outlive the process is kept on disk in ``state_dir``: whether a run had the
stage armed or an operator had stopped it (``stage-state.json``: a stage service killed
mid-run comes back **held** until a controller claims it or an operator resumes it,
never ``ready`` under a run that may still be going), and every line exchanged with the
amplifier (``stage-commands.jsonl``, so a run's command log survives a restart).

The amplifier is read back every ``READBACK_S``; outputs that differ from what this
service last commanded (a front-panel knob, a second serial client) **stop** the stage
with the reason, and the model follows the measured voltages.
"""

from __future__ import annotations

import collections
import copy
import json
import logging
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

from semservo import nv40
from semservo.errors import CommandError
from semservo.instruments import (
    STAGE_DRIVER_GROUP, DeviceError, LinkError, LogEntry, RotationStageDriver, StageDriver, load_plugin,
)
from semservo.stage_model import BranchModel, load_model

log = logging.getLogger("stage")

#: Back-off between reconnection attempts after the link is lost (seconds).
RECONNECT_BACKOFF_S = (0.25, 0.5, 1.0, 2.0, 4.0)
#: How often the amplifier's outputs are read back and compared with what was commanded
#: (also how a pulled cable is seen when nothing moves): while a run has it armed, idle.
READBACK_S = {True: 0.25, False: 1.0}
#: Read-back further than this from the commanded voltage is a change nobody commanded
#: (the emulator and the NV 40/3 read back to 1 mV; knob noise stays far below this).
UNCOMMANDED_V = 0.05
#: A piezo stage settles within milliseconds of a step (the TRITOR's resonance is near 1 kHz);
#: creep goes on for longer, which the loop measures and corrects.
DEFAULT_SETTLE_S = 0.01
#: A move's voltage step may be at most this factor times the model's steepest slope
#: times the move, plus this slack (V): room for a reversal's minor loop, never for a jump.
MODEL_STEP_FACTOR = 3.0
MODEL_STEP_SLACK_V = 1.0
#: The command log kept in memory and reloaded from disk at start.
COMMAND_LOG_KEPT = 20_000


class Refused(CommandError):
    """A command the stage will not carry out; ``code`` says which rule."""

    def __str__(self) -> str:
        return self.message


@dataclass(frozen=True)
class StageLimits:
    voltage_min: float = nv40.LAB_SAFE_VOLTAGE[0]
    voltage_max: float = nv40.LAB_SAFE_VOLTAGE[1]
    travel_min_um: float = 0.0
    travel_max_um: float = 100.0
    max_step_v: float = 25.0
    max_rate_v_per_s: float = 200.0
    #: The largest turn or tilt one command may ask (degrees).
    max_turn_deg: float = 30.0


@dataclass
class Watchdog:
    timeout_s: float = 0.0
    owner: str | None = None
    last_contact: float = 0.0

    @property
    def armed(self) -> bool:
        return self.timeout_s > 0


@dataclass
class StageCore:
    url: str
    limits: StageLimits = field(default_factory=StageLimits)
    channels: dict[str, int] = field(default_factory=lambda: {"x": 0, "y": 1})
    models: dict = field(default_factory=dict)  # axis -> BranchModel | LinearModel
    clock: Callable[[], float] = time.monotonic
    open_driver: Callable[[str], StageDriver] = field(default_factory=lambda: driver_class("nv40").open)
    state_dir: Path | None = None  # None: nothing survives the process (tests of the core)
    #: The rotation-and-tilt stage, if the lab has one (every rule of a move applies).
    rotation: RotationStageDriver | None = None
    #: Seconds each axis takes to settle after a move (a frame scanned before shows it
    #: moving); axes not named take ``DEFAULT_SETTLE_S``.
    settle_s: dict[str, float] = field(default_factory=dict)

    def __post_init__(self):
        for axis in self.channels:
            self.models.setdefault(axis, BranchModel.tritor(axis if axis in ("x", "y") else "x"))
        self.driver: StageDriver | None = None
        self.link = "connecting"
        self.state = "ready"  # ready | stopped | held
        self.state_reason = ""
        #: Who stopped it: "request" (a stop command: an operator, the gateway, a script)
        #: or "stage" (this service's own checks: outputs it did not command, a release).
        self.stopped_by: str | None = None
        self.device: dict = {}
        self.device_limits: tuple[float, float] = (nv40.VOLTAGE_MIN, nv40.VOLTAGE_MAX)
        self.voltages: dict[str, float] = {}
        self.last_write: dict[str, float] = {}
        self.watchdog = Watchdog()
        self.last_error: str | None = None
        self.attempts = 0
        self.next_attempt = 0.0
        self.last_io = 0.0
        self.counters = {"moves": 0, "turns": 0, "refused": 0, "link_lost": 0, "reconnects": 0,
                         "uncommanded_changes": 0}
        self.log_archive: list = []  # entries of drivers closed after a link loss, and of earlier processes
        #: When the last move, turn or voltage write has settled (Unix ns; 0: none since
        #: the start): frames scanned before it show a pose in between (a teach waits).
        self.settled_at_ns = 0
        self.rotation_angles: dict[str, float] | None = None  # as last read (see _rotation_state)
        self.rotation_travel: dict[str, list[float]] = {}
        self.rotation_targets: dict[str, float] = {}  # where the last commands sent each axis
        # Until then (monotonic) the rotation stage is on its way: poll reads its angles.
        self.rotation_moving_until = 0.0
        self.rotation_read_at = 0.0
        self.rotation_link = "not used yet"
        self._log_file = None
        self._restore()

    # -- what survives a restart ---------------------------------------------------------
    @property
    def _state_path(self) -> Path | None:
        return None if self.state_dir is None else self.state_dir / "stage-state.json"

    def _restore(self) -> None:
        """Come back as the last process left things: held if a run had the stage armed,
        stopped if an operator had stopped it; and with the command log so far."""
        if self.state_dir is None:
            return
        self.state_dir.mkdir(parents=True, exist_ok=True)
        log_path = self.state_dir / "stage-commands.jsonl"
        if log_path.is_file():
            with open(log_path, encoding="utf-8") as lines:
                kept = collections.deque(lines, maxlen=COMMAND_LOG_KEPT)  # the tail, not the whole file
            for line in kept:
                try:
                    self.log_archive.append(LogEntry(**json.loads(line)))
                except (ValueError, TypeError):
                    continue  # the line being written when the process died
            if len(kept) == COMMAND_LOG_KEPT:  # keep the file from growing without end
                log_path.write_text("".join(kept), encoding="utf-8")
        self._log_file = open(log_path, "a", encoding="utf-8")  # noqa: SIM115 - open for the process's life
        try:
            saved = json.loads(self._state_path.read_text())
        except (OSError, ValueError):
            return
        if saved.get("armed_by"):
            self.state = "held"
            self.state_reason = (f"the stage service restarted while run owner {saved['armed_by']} had it armed: "
                                 f"held until a controller claims it (a new run) or an operator resumes")
            log.warning("%s", self.state_reason)
        elif saved.get("state") == "stopped":
            self.state, self.state_reason = "stopped", f"{saved.get('reason', 'stopped')} (before a restart)"
            self.stopped_by = saved.get("stopped_by") or "stage"

    def _persist(self) -> None:
        if self._state_path is None:
            return
        state = {"state": self.state, "reason": self.state_reason, "stopped_by": self._stopped_by(),
                 "armed_by": self.watchdog.owner if self.watchdog.armed else None}
        temporary = self._state_path.with_suffix(f".{os.getpid()}.tmp")
        temporary.write_text(json.dumps(state))
        temporary.replace(self._state_path)

    def _journal_entry(self, entry: LogEntry) -> None:
        if self._log_file is not None:
            self._log_file.write(json.dumps(asdict(entry)) + "\n")
            self._log_file.flush()  # in the OS's hands: survives a killed process

    def shutdown(self) -> None:
        """An orderly end: nothing is left armed by a run (its controller stopped first),
        so the next process starts ready, unless the stage was stopped (an operator, an
        uncommanded change): a stop holds until someone resumes, across an orderly
        restart too (``docker compose down`` and ``up``). The link and the log file are closed."""
        if not self.watchdog.armed and self._state_path is not None:
            if self.state == "stopped":
                self._persist()
            else:
                self._state_path.unlink(missing_ok=True)
        self.close()
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None

    # -- the link ----------------------------------------------------------------------
    def connect(self) -> bool:
        """Open the port, identify the amplifier, take remote control of our channels,
        read its limits and the current outputs. False (and the reason in health) if
        any of it fails. The rotation stage, if any, is read at the first connect only
        (reconnecting after a lost serial link must not also wait on its link); a
        failure there is reported in ``state``, not a failure of the stage."""
        if self.rotation_link == "not used yet":
            self._read_rotation_stage()
        self.close()
        try:
            self.driver = self.open_driver(self.url)
            self.driver.on_entry = self._journal_entry
            self.device = self.driver.identify()
            self.driver.take_control(list(self.channels.values()))
            self.device_limits = tuple(self.driver.output_limits())
            measured = self.driver.read_outputs()
        except (LinkError, DeviceError) as error:
            self._lost(f"cannot connect to {self.url}: {error}")
            return False
        before = dict(self.voltages)  # empty at the first connection
        self.voltages = {axis: measured[channel] for axis, channel in self.channels.items()}
        for axis, model in self.models.items():
            model.follow_voltage(self.voltages[axis], self.voltages[axis])
        changed = {axis: (before[axis], self.voltages[axis]) for axis in before
                   if abs(self.voltages[axis] - before[axis]) > UNCOMMANDED_V}
        if self.link != "connected" and self.counters["link_lost"]:
            self.counters["reconnects"] += 1
        self.link, self.attempts, self.last_error = "connected", 0, None
        self.last_io = self.clock()
        log.info("stage driver %s (%s): %s, output range %s", type(self.driver).__name__, self.url,
                 self.device.get("model"), self.device_limits)
        # Power-cycled, or moved by hand, while the link was down: the stage is not where
        # anything believes it is.
        self._uncommanded(changed, "while the serial link was down", "power-cycled or moved by hand")
        return True

    def close(self) -> None:
        """Close the serial port (its command log is kept)."""
        if self.driver is not None:
            self.log_archive.extend(self.driver.log)
            try:
                self.driver.close()
            except Exception:  # noqa: BLE001 - a dead port may fail to close; it is gone either way
                log.debug("closing the old port failed", exc_info=True)
            self.driver = None

    def _lost(self, reason: str) -> None:
        if self.link == "connected":
            self.counters["link_lost"] += 1
            log.error("serial link lost: %s", reason)
        elif reason != self.last_error:
            # Never connected, or a new reason: said once, not only in health (a stage
            # on a missing /dev/ttyUSB0 logged "ready" and nothing else).
            log.warning("serial link not up: %s; retrying with back-off", reason)
        self.link = "lost"
        self.last_error = reason
        delay = RECONNECT_BACKOFF_S[min(self.attempts, len(RECONNECT_BACKOFF_S) - 1)]
        self.attempts += 1
        self.next_attempt = self.clock() + delay

    def _io(self, action: Callable[[StageDriver], object]):
        """Run one exchange with the amplifier; a link failure is recorded and raised as
        :class:`Refused` with code ``link_lost``."""
        if self.link != "connected" or self.driver is None:
            raise Refused("link_lost", f"serial link to {self.url} is down: {self.last_error}")
        try:
            result = action(self.driver)
        except LinkError as error:
            self._lost(str(error))
            raise Refused("link_lost", f"serial link to {self.url} lost: {error}") from None
        self.last_io = self.clock()
        return result

    def poll(self) -> float:
        """Periodic work: reconnect with back-off, check an idle link, run the watchdog.
        Returns the seconds until it is due again."""
        now = self.clock()
        if self.link != "connected":
            if now >= self.next_attempt:
                self.connect()
            return max(0.05, self.next_attempt - self.clock()) if self.link != "connected" else 0.1
        if self.watchdog.armed and self.state == "ready" and now - self.watchdog.last_contact > self.watchdog.timeout_s:
            self.state = "held"
            self.state_reason = (f"watchdog: {self.watchdog.owner or 'the controller'} silent for "
                                 f"{now - self.watchdog.last_contact:.2f} s; holding at {self._voltages_text()}")
            self.watchdog = Watchdog()
            self._persist()
            log.warning("%s", self.state_reason)
            self._halt_rotation()  # a turn still on its way stops too
        self._follow_rotation()
        if now - self.last_io > READBACK_S[self.watchdog.armed]:
            try:
                measured = self._io(self._read_back)
            except Refused:
                return 0.05
            self._compare(measured)
        return 0.05 if self.watchdog.armed else 0.2

    def _read_back(self, driver):
        """What the driver says it outputs now (a motion driver: where its axes are)."""
        return driver.read_outputs()

    def _compare(self, measured) -> None:
        """Outputs this service did not command: stop, say what changed, follow them."""
        changed = {axis: (self.voltages[axis], measured[channel]) for axis, channel in self.channels.items()
                   if abs(measured[channel] - self.voltages[axis]) > UNCOMMANDED_V}
        for axis, (before, after) in changed.items():
            self.models[axis].follow_voltage(after, before)
            self.voltages[axis] = after
        self._uncommanded(changed, "without a command from semservo", "a front-panel knob or another serial client")

    def _uncommanded(self, changed: dict[str, tuple[float, float]], when: str, suspects: str) -> None:
        """Outputs changed that this service did not command: stop, and say what changed."""
        if not changed:
            return
        self.counters["uncommanded_changes"] += 1
        what = ", ".join(f"{axis} {before:.3f} -> {after:.3f} V" for axis, (before, after) in changed.items())
        self.stop(f"the amplifier's outputs changed {when} ({what}): {suspects}? Check the stage, then resume")

    # -- commands ----------------------------------------------------------------------
    def _voltages_text(self) -> str:
        return ", ".join(f"{axis} {volts:.3f} V" for axis, volts in self.voltages.items())

    def _check_owner(self, owner: str | None) -> None:
        if self.watchdog.armed and owner != self.watchdog.owner:
            raise Refused("owned", f"a run ({self.watchdog.owner}) is moving the stage; stop it first "
                                   f"(this request came from {owner or 'an unnamed client'})")

    def _check_state(self) -> None:
        if self.state == "stopped":
            raise Refused("stopped", f"the stage is stopped ({self.state_reason}); resume first",
                          reason=self.state_reason, stopped_by=self.stopped_by)
        if self.state == "held":
            raise Refused("held", f"the stage is held: {self.state_reason}")

    def _check_ready(self) -> None:
        self._check_state()
        if self.link != "connected":
            raise Refused("link_lost", f"serial link to {self.url} is down: {self.last_error}")

    def _check_voltages(self, volts: dict[str, float], now: float) -> None:
        low = max(self.limits.voltage_min, self.device_limits[0])
        high = min(self.limits.voltage_max, self.device_limits[1])
        for axis, value in volts.items():
            if axis not in self.channels:
                raise Refused("bad_axis", f"unknown axis {axis!r}; axes: {', '.join(self.channels)}")
            if not low <= value <= high:
                raise Refused("voltage_limit", f"{axis}: {value:.3f} V is outside the soft limits {low:g}..{high:g} V")
            step = abs(value - self.voltages[axis])
            if step > self.limits.max_step_v:
                raise Refused("step_limit", f"{axis}: a {step:.2f} V step exceeds the maximum of "
                                            f"{self.limits.max_step_v:g} V per command")
            since = now - self.last_write.get(axis, -1e9)
            if step > 0 and step / max(since, 1e-6) > self.limits.max_rate_v_per_s:
                raise Refused("rate_limit", f"{axis}: {step:.2f} V {since * 1000:.1f} ms after the last write exceeds "
                                            f"{self.limits.max_rate_v_per_s:g} V/s")

    def _check_model_step(self, goal: dict[str, float], volts: dict[str, float]) -> None:
        """A model that asks for far more voltage than the move's size can need is not to
        be trusted: refused, said, nothing written (a model out of step with its axis once
        turned a 0.03 um correction into an 11 V jump, a 70 px leap of the view)."""
        for axis, target in goal.items():
            model = self.models[axis]
            moved_um = abs(target - model.position_um)
            allowed_v = MODEL_STEP_SLACK_V + MODEL_STEP_FACTOR * model.max_slope_v_per_um() * moved_um
            step_v = abs(volts[axis] - self.voltages.get(axis, volts[axis]))
            if step_v > allowed_v:
                raise Refused("model_jump", f"{axis}: the displacement model asks for a {step_v:.2f} V step for a "
                                            f"{moved_um:.3f} um move (at most {allowed_v:.2f} V is plausible): the "
                                            f"model is out of step with the axis; stop, check, resume")

    def _write(self, volts: dict[str, float], owner: str | None) -> dict:
        now = self.clock()
        written_at_ns = time.time_ns()
        readback = self._io(lambda driver: driver.write_outputs({self.channels[a]: v for a, v in volts.items()}))
        for axis, value in volts.items():
            self.voltages[axis] = readback[self.channels[axis]]
            self.last_write[axis] = now
        if owner is not None and owner == self.watchdog.owner:
            self.watchdog.last_contact = now
        self.counters["moves"] += 1
        mismatch = {axis: self.voltages[axis] for axis, value in volts.items() if abs(self.voltages[axis] - value) > 0.01}
        if mismatch:
            # The amplifier did not take the set point (e.g. a channel under knob control).
            raise Refused("not_applied", f"the amplifier reads back {mismatch} instead of {volts}")
        settle_s = max(self.settle_s.get(axis, DEFAULT_SETTLE_S) for axis in volts)
        return {"written_at_ns": written_at_ns, "voltages": dict(self.voltages), "positions_um": self.positions(),
                "settled_at_ns": written_at_ns + int(settle_s * 1e9),
                # Any step the step limit allows is within the rate limit from then on (the
                # next command's step is not known here: pieces equal in um are not in volts).
                "ready_at_ns": written_at_ns + int(self.limits.max_step_v / self.limits.max_rate_v_per_s * 1e9) + 1}

    def positions(self) -> dict[str, float]:
        return {axis: model.position_um for axis, model in self.models.items()}

    def move(self, targets: dict[str, float], *, relative: bool = False, owner: str | None = None) -> dict:
        """Move axes to ``targets`` (um, absolute travel as the model estimates it) or
        by them (``relative``), through the displacement-voltage model."""
        try:
            self._check_ready()
            self._check_owner(owner)
            travel = {axis: (self.limits.travel_min_um, self.limits.travel_max_um) for axis in self.models}
            here = {axis: model.position_um for axis, model in self.models.items()}
            goal = _goals(targets, relative, here, travel, "travel_limit", "um")
            # Voltages from a copy of each model: a refused move must not change its state.
            volts = {axis: copy.copy(self.models[axis]).voltage_for(value) for axis, value in goal.items()}
            self._check_model_step(goal, volts)
            try:
                self._check_voltages(volts, self.clock())
            except Refused as refusal:
                raise self._in_micrometres(refusal, goal, volts, here) from None
        except Refused:
            self.counters["refused"] += 1
            raise
        result = self._write(volts, owner)
        for axis, value in goal.items():
            self.models[axis].voltage_for(value)  # commit: position and branch direction
        result["positions_um"] = self.positions()
        return result

    def _in_micrometres(self, refusal: Refused, goal: dict[str, float], volts: dict[str, float],
                        here: dict[str, float]) -> Refused:
        """A move refused for its voltage step, said in the unit it was asked in: how far
        one command may move each axis from here (the step limit is in volts, the
        request in micrometres: a user who asked for 30 um learned only that 31.5 V is
        over 25 V). Proportional: the model is near linear over one step."""
        if refusal.code != "step_limit":
            return refusal
        largest = []
        for axis, target in goal.items():
            step_v = abs(volts[axis] - self.voltages[axis])
            if step_v > self.limits.max_step_v:
                moved_um = abs(target - here[axis])
                largest.append(f"{axis} about {moved_um * self.limits.max_step_v / step_v:.1f} um")
        if not largest:
            return refusal
        return Refused(refusal.code, f"{refusal.message}: one move may take {', '.join(largest)} from here "
                                     "(move in pieces)", **refusal.extra)

    def set_voltages(self, volts: dict[str, float], *, owner: str | None = None) -> dict:
        """Raw voltages (calibration, the paper's homing), same limits as a move. The
        model's position follows the model's inverse on the branch of the move."""
        try:
            self._check_ready()
            self._check_owner(owner)
            self._check_voltages(volts, self.clock())
        except Refused:
            self.counters["refused"] += 1
            raise
        before = dict(self.voltages)
        result = self._write(volts, owner)
        for axis in volts:
            self.models[axis].follow_voltage(self.voltages[axis], before[axis])
        result["positions_um"] = self.positions()
        return result

    def rotate(self, targets: dict[str, float], *, relative: bool = False, owner: str | None = None) -> dict:
        """Turn or tilt the rotation-and-tilt stage to ``targets`` (degrees, by axis:
        ``rotation_deg`` about the beam, ``tilt_x_deg``, ``tilt_y_deg``) or by them
        (``relative``). The rules of a move apply: not stopped or held, the run's owner
        only, finite, within the stage's travel, at most ``max_turn_deg`` per command;
        refused whole, never clipped."""
        try:
            self._check_state()
            self._check_owner(owner)
            if self.rotation is None:
                raise Refused("no_rotation_stage", "this lab has no rotation-and-tilt stage "
                                                   "(SEMSERVO_STAGE__ROTATION_STAGE)")
            travel = self._rotation_io(self.rotation.travel)
            self.rotation_travel = {axis: list(span) for axis, span in travel.items()}
            current = self.rotation_angles = self._rotation_io(self.rotation.read_angles)
            # Relative to where the last command sent it (a stage that is still on its way,
            # or inside its gear's play, is not yet there: adding to its angle now would
            # drop what remains of the last move).
            base = {**current, **self.rotation_targets}
            goal = _goals(targets, relative, base, travel, "rotation_limit", "degrees")
            for axis in goal:
                if abs(goal[axis] - base[axis]) > self.limits.max_turn_deg:
                    raise Refused("step_limit", f"{axis}: a {abs(goal[axis] - base[axis]):.3f} degree turn "
                                                f"exceeds the maximum of {self.limits.max_turn_deg:g} per command")
        except Refused:
            self.counters["refused"] += 1
            raise
        written_at_ns = time.time_ns()
        angles = self.rotation_angles = self._rotation_io(lambda: self.rotation.move_to(goal))
        self.rotation_targets.update(goal)
        settles = getattr(self.rotation, "settles_in_s", None)
        settles_in_s = float(settles()) if callable(settles) else 0.0
        self.rotation_moving_until = time.monotonic() + settles_in_s
        if owner is not None and owner == self.watchdog.owner:
            self.watchdog.last_contact = self.clock()
        self.counters["turns"] += 1
        # Until then the stage is still turning: frames scanned meanwhile show a pose in between.
        return {"written_at_ns": written_at_ns, "angles_deg": angles, "targets_deg": {**angles, **goal},
                "settled_at_ns": written_at_ns + int(settles_in_s * 1e9)}

    def _rotation_io(self, action: Callable[[], object]):
        """A call to the rotation stage; its failures become refusals with the reason."""
        try:
            result = action()
        except LinkError as error:
            self.last_error = f"rotation stage: {error}"
            self.rotation_link = f"lost: {error}"
            raise Refused("rotation_link_lost", str(error)) from None
        except DeviceError as error:
            raise Refused("device_refused", str(error)) from None
        self.rotation_link = "connected"
        return result

    def heartbeat(self, owner: str | None = None) -> dict:
        if owner is not None and owner == self.watchdog.owner:
            self.watchdog.last_contact = self.clock()
        return {"state": self.state, "reason": self.state_reason, "stopped_by": self._stopped_by(),
                "watchdog": self.watchdog.armed, "owner": self.watchdog.owner}

    def _stopped_by(self) -> str | None:
        return self.stopped_by if self.state == "stopped" else None

    def arm(self, timeout_s: float, owner: str) -> dict:
        """A run starts: hold if ``owner`` is silent for ``timeout_s``. Clears a hold."""
        if not 0.05 <= timeout_s <= 600:
            raise Refused("bad_request", f"watchdog timeout must be 0.05..600 s, got {timeout_s}")
        if self.state == "stopped":
            raise Refused("stopped", f"the stage is stopped ({self.state_reason}); resume first",
                          reason=self.state_reason, stopped_by=self.stopped_by)
        if self.watchdog.armed and owner != self.watchdog.owner:
            raise Refused("owned", f"run owner {self.watchdog.owner} has the stage armed; it must stop first")
        self.watchdog = Watchdog(timeout_s, owner, self.clock())
        self.state, self.state_reason = "ready", ""
        self._persist()
        return self.describe()

    def disarm(self, owner: str | None = None) -> dict:
        if owner is None or owner == self.watchdog.owner:
            self.watchdog = Watchdog()
            self._persist()
        return self.describe()

    def stop(self, reason: str = "stop requested", *, by: str = "stage") -> dict:
        """Hold at once and refuse moves until :meth:`resume`. Works in any state, link
        up or not. The driver's ``halt`` stops motion in progress (the NV 40/3 sends
        nothing: an amplifier keeps its outputs). ``by``: "request" for a stop command,
        "stage" for this service's own (the run it ends failed, not stopped)."""
        self.state, self.state_reason, self.stopped_by = "stopped", reason, by
        self.watchdog = Watchdog()
        self._persist()
        log.warning("stage stopped: %s", reason)
        if self.driver is not None and self.link == "connected":
            try:  # a controller with motion in progress halts it; an amplifier has none
                self.driver.halt()
            except (LinkError, DeviceError) as error:
                self.last_error = f"stopped, but the driver's halt failed: {error}"
                log.error("%s", self.last_error)
        self._halt_rotation()
        return self.describe()

    def _follow_rotation(self) -> None:
        """While the rotation stage is on its way, read its angles every 0.1 s (and once
        after it has arrived), so the state shows where it is, not where it was."""
        moment = time.monotonic()
        if self.rotation is None or moment > self.rotation_moving_until + 0.3 or moment - self.rotation_read_at < 0.1:
            return
        self.rotation_read_at = moment
        try:
            self.rotation_angles = self._rotation_io(self.rotation.read_angles)
        except Refused as refusal:
            log.warning("rotation stage: %s", refusal)

    def _halt_rotation(self) -> None:
        if self.rotation is None:
            return
        self.rotation_targets.clear()  # it stops where it is
        try:
            self.rotation.halt()
        except (LinkError, DeviceError) as error:
            self.last_error = f"the rotation stage's halt failed: {error}"
            log.error("%s", self.last_error)

    def resume(self) -> dict:
        self.state, self.state_reason = "ready", ""
        self._persist()
        return self.describe()

    def release(self) -> dict:
        """Give the channels back to the front-panel knobs, and stop."""
        self._io(lambda driver: driver.release(list(self.channels.values())))
        return self.stop("released to the front panel")

    def command_log(self, since_ns: int = 0, limit: int = 5000) -> list[dict]:
        entries = self.log_archive + (self.driver.log if self.driver else [])
        return [{"time_ns": entry.time_ns, "direction": entry.direction, "text": entry.text}
                for entry in entries if entry.time_ns >= since_ns][-limit:]

    def describe(self) -> dict:
        return {
            "url": self.url, "link": self.link, "state": self.state, "reason": self.state_reason,
            "stopped_by": self._stopped_by(),
            "device": self.device.get("model"), "voltages": dict(self.voltages), "positions_um": self.positions(),
            "limits": {**asdict(self.limits), "device_voltage": list(self.device_limits)},
            "watchdog": {"armed": self.watchdog.armed, "timeout_s": self.watchdog.timeout_s,
                         "owner": self.watchdog.owner},
            "models": {axis: model.to_dict()["kind"] for axis, model in self.models.items()},
            "settle_s": {axis: self.settle_s.get(axis, DEFAULT_SETTLE_S) for axis in self.channels},
            "rotation": self._rotation_state(), "settled_at_ns": self.settled_at_ns,
            "last_error": self.last_error, **self.counters,
        }


    def _read_rotation_stage(self) -> None:
        if self.rotation is None:
            return
        try:
            self._rotation_io(lambda: self.rotation_travel.update(
                {axis: list(span) for axis, span in self.rotation.travel().items()}))
            self.rotation_angles = self._rotation_io(self.rotation.read_angles)
        except Refused as refusal:
            log.warning("rotation stage: %s", refusal)

    def _rotation_state(self) -> dict | None:
        """The rotation-and-tilt stage as last read (at its first use and after every
        turn: never read here, so a state or a stop never waits on its link); None when
        the lab has none."""
        if self.rotation is None:
            return None
        return {"angles_deg": self.rotation_angles, "travel_deg": self.rotation_travel, "link": self.rotation_link}


def _goals(targets: dict[str, float], relative: bool, here: dict[str, float], travel: dict[str, tuple[float, float]],
           limit_code: str, unit: str) -> dict[str, float]:
    """Where each axis is asked to go (``targets`` are steps from ``here`` when
    ``relative``), each checked against its travel: a move and a turn follow one rule."""
    goal = {}
    for axis, value in targets.items():
        if axis not in travel:
            raise Refused("bad_axis", f"unknown axis {axis!r}; axes: {', '.join(travel)}")
        goal[axis] = here[axis] + value if relative else value
        low, high = travel[axis]
        if not low <= goal[axis] <= high:  # NaN fails this too
            raise Refused(limit_code, f"{axis}: {goal[axis]:.4g} {unit} is outside the travel {low:g}..{high:g} {unit}")
    return goal


def models_from(paths: dict[str, str | None], axes) -> dict:
    """The default TRITOR branches per axis, or a model file (JSON, as written by
    :func:`semservo.stage_model.save_model`) where one is given."""
    return {axis: load_model(paths[axis]) if paths.get(axis) else BranchModel.tritor(axis) for axis in axes}


def driver_class(name: str) -> type:
    """The stage driver ``name`` names: an entry point of ``semservo.stage_drivers``
    (semservo's own: ``nv40``, ``simulated``) or ``package.module:ClassName``."""
    return load_plugin(name, STAGE_DRIVER_GROUP)
