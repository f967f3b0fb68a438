"""A simulated closed-loop positioner in the motion driver interface, in-process.

The motion driver beside :class:`semservo.openfibsem.OpenFibsemMotion`, as the simulated
amplifier sits beside the NV 40/3: axes that take micrometres (a closed-loop stage, x
and y) and a beam shift (``beam_x``, ``beam_y``, a small travel), each reporting its
position. The stage service runs on it (``SEMSERVO_STAGE__DRIVER=simulated-positioner``)
to try a configuration dry, and the tests use it to check that the stage's rules hold
for a driver in physical units. It moves no simulated sample.

Devices are kept per URL, so reopening one (a reconnect) finds its axes where they
were. ``plugged`` and ``positions`` are there for tests to pull the cable or move an
axis by hand; the device refuses a move beyond its travel in its own words, as a
vendor's controller does.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from typing import ClassVar

from semservo.instruments import PHYSICAL, Axis, DeviceError
from semservo.simulation.in_memory import InMemoryDriver

#: The simulated device's axes: a closed-loop stage with 100 um of travel, and a beam
#: shift of +-5 um.
AXES = {"x": Axis("um", "stage", (-50.0, 50.0)), "y": Axis("um", "stage", (-50.0, 50.0)),
        "beam_x": Axis("um", "beam", (-5.0, 5.0)), "beam_y": Axis("um", "beam", (-5.0, 5.0))}


@dataclass
class SimulatedPositionerDevice:
    """The positioner itself: what outlives a connection."""

    positions: dict[str, float] = field(default_factory=lambda: dict.fromkeys(AXES, 0.0))
    plugged: bool = True
    halts: int = 0
    moves: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)


class SimulatedPositioner(InMemoryDriver):
    """A :class:`~semservo.instruments.MotionDriver` held in memory."""

    kind = PHYSICAL
    device_type = SimulatedPositionerDevice
    what = "simulated positioner"
    devices: ClassVar[dict[str, SimulatedPositionerDevice]] = {}

    def identify(self) -> dict:
        self._exchange("identify", self.what)
        return {"model": self.what}

    def axes(self) -> dict[str, Axis]:
        return dict(AXES)

    def read_positions(self) -> dict[str, float]:
        with self.device.lock:
            positions = dict(self.device.positions)
        self._exchange("read", " ".join(f"{axis}={value:.4f}" for axis, value in positions.items()))
        return positions

    def move_by(self, steps: dict[str, float]) -> dict[str, float]:
        with self.device.lock:
            for axis, step in steps.items():
                if axis not in AXES:
                    raise DeviceError(f"no axis {axis!r}")
                goal = self.device.positions[axis] + step
                low, high = AXES[axis].travel
                if not (math.isfinite(goal) and low <= goal <= high):
                    raise DeviceError(f"{axis}: {goal:.4f} um is out of range [{low:g}, {high:g}]")
            for axis, step in steps.items():
                self.device.positions[axis] += step
            self.device.moves += 1
            self._exchange("move " + " ".join(f"{axis}{step:+.4f}" for axis, step in steps.items()), "ok")
        return self.read_positions()

    def halt(self) -> None:
        self.device.halts += 1

    def close(self) -> None:
        """Nothing to close: the device keeps its positions."""
