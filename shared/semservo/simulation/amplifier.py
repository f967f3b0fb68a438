"""A simulated amplifier in the stage driver interface, in-process: no serial link.

The stage driver beside :class:`semservo.nv40_driver.NV403Driver`, as a simulated
motor sits beside a real one: same interface, no hardware. The stage service runs
on it (``SEMSERVO_STAGE__DRIVER=simulated``) to try a configuration dry, and the tests
use it to check that the stage's safety rules hold for any driver. It does not move a
simulated sample (the fake lab's emulated NV 40/3 does that, over a real serial link).

Devices are kept per URL, so reopening one (a reconnect) finds its outputs as they
were, as a real amplifier keeps them. ``plugged`` and ``outputs`` are there for tests
to pull the cable or turn a knob.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import ClassVar

from semservo.instruments import DeviceError
from semservo.simulation.in_memory import InMemoryDriver

CHANNELS = (0, 1, 2)
OUTPUT_RANGE = (-20.0, 130.0)


@dataclass
class SimulatedDevice:
    """The amplifier itself: what outlives a connection."""

    outputs: dict[int, float] = field(default_factory=lambda: dict.fromkeys(CHANNELS, 0.0))
    remote: dict[int, bool] = field(default_factory=lambda: dict.fromkeys(CHANNELS, False))
    plugged: bool = True
    halts: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)


class SimulatedAmplifier(InMemoryDriver):
    """A three-channel amplifier with the :class:`~semservo.instruments.StageDriver`
    methods, held in memory."""

    device_type = SimulatedDevice
    what = "simulated amplifier"
    devices: ClassVar[dict[str, SimulatedDevice]] = {}

    def identify(self) -> dict:
        self._exchange("identify", self.what)
        return {"model": self.what, "channels": len(CHANNELS)}

    def take_control(self, channels: list[int]) -> None:
        with self.device.lock:
            self._exchange(f"remote {list(channels)}", "ok")
            for channel in channels:
                self.device.remote[channel] = True

    def release(self, channels: list[int]) -> None:
        with self.device.lock:
            self._exchange(f"local {list(channels)}", "ok")
            for channel in channels:
                self.device.remote[channel] = False

    def output_limits(self) -> tuple[float, float]:
        self._exchange("limits", f"{OUTPUT_RANGE[0]} {OUTPUT_RANGE[1]}")
        return OUTPUT_RANGE

    def read_outputs(self) -> dict[int, float]:
        with self.device.lock:
            outputs = dict(self.device.outputs)
        self._exchange("read", " ".join(f"{outputs[c]:.3f}" for c in CHANNELS))
        return outputs

    def write_outputs(self, values: dict[int, float]) -> dict[int, float]:
        with self.device.lock:
            for channel, value in values.items():
                if channel not in CHANNELS:
                    raise DeviceError(f"no channel {channel}")
                if not self.device.remote[channel]:
                    continue  # under front-panel control: the set point is ignored, as on the device
                self.device.outputs[channel] = min(max(float(value), OUTPUT_RANGE[0]), OUTPUT_RANGE[1])
            self._exchange("set " + " ".join(f"{c}={v:.3f}" for c, v in values.items()), "ok")
        return self.read_outputs()

    def halt(self) -> None:
        self.device.halts += 1

    def close(self) -> None:
        """Nothing to close: the device keeps its outputs."""
