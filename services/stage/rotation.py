"""The fake lab's rotation-and-tilt stage, as the stage service drives it: over the fake
lab's control socket, as a vendor's goniometer controller would be driven over its own
link. A real one plugs in as another :class:`semservo.instruments.RotationStageDriver`.
"""

from __future__ import annotations

import time

from semservo.instruments import DeviceError, LinkError
from semservo.simulation.world import ROTATION_STAGE_LIMITS_DEG
from semservo.transport import CommandError, ControlClient, ServiceUnavailable


class FakelabRotationStage:
    """:class:`semservo.instruments.RotationStageDriver` for the simulated stage (it
    moves at a finite speed, with backlash: :mod:`semservo.simulation.goniometer`)."""

    def __init__(self, client: ControlClient):
        self.client = client
        self.settles_at = 0.0  # monotonic time at which the last move has arrived

    def _request(self, **args) -> dict[str, float]:
        try:
            reply = self.client.request("set_rotation_stage", **args)
        except ServiceUnavailable as error:
            raise LinkError(f"the rotation stage (fake lab) does not answer: {error}") from None
        except CommandError as error:
            raise DeviceError(f"the rotation stage refused: {error.message}") from None
        self.settles_at = time.monotonic() + float(reply.get("settles_in_s", 0.0))
        return {axis: float(value) for axis, value in reply.items() if axis in ROTATION_STAGE_LIMITS_DEG}

    def travel(self) -> dict[str, tuple[float, float]]:
        return dict(ROTATION_STAGE_LIMITS_DEG)

    def read_angles(self) -> dict[str, float]:
        return self._request()

    def move_to(self, angles: dict[str, float]) -> dict[str, float]:
        self._request(**angles)
        return self.read_angles()

    def settles_in_s(self) -> float:
        return max(self.settles_at - time.monotonic(), 0.0)

    def halt(self) -> None:
        self._request(halt=True)

    def close(self) -> None:
        self.client.close()


class WorldRotationStage:
    """:class:`semservo.instruments.RotationStageDriver` on a simulated world in this
    process (the same stage the fake lab serves; for tests of the stage's core)."""

    def __init__(self, world):
        self.world = world

    def travel(self) -> dict[str, tuple[float, float]]:
        return dict(ROTATION_STAGE_LIMITS_DEG)

    def read_angles(self) -> dict[str, float]:
        return dict(self.world.rotation_stage)

    def move_to(self, angles: dict[str, float]) -> dict[str, float]:
        try:
            self.world.set_rotation_stage(**angles)
        except ValueError as error:
            raise DeviceError(str(error)) from None
        return self.read_angles()

    def settles_in_s(self) -> float:
        return self.world.rotation_stage_settles_in_s()

    def halt(self) -> None:
        self.world.halt_rotation_stage()

    def close(self) -> None:
        """Nothing to close."""
