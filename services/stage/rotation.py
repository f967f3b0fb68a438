"""The fake lab's rotation-and-tilt stage, as the stage service drives it: over the fake
lab's control socket, as a vendor's goniometer controller would be driven over its own
link. A real one plugs in as another :class:`semservo.instruments.RotationStageDriver`.
"""

from __future__ import annotations

from semservo.instruments import DeviceError, LinkError
from semservo.simulation.world import ROTATION_STAGE_LIMITS_DEG
from semservo.transport import CommandError, ControlClient, ServiceUnavailable


class FakelabRotationStage:
    """:class:`semservo.instruments.RotationStageDriver` for the simulated stage."""

    def __init__(self, client: ControlClient):
        self.client = client

    def _request(self, **angles: float) -> dict[str, float]:
        try:
            return {axis: float(value) for axis, value in self.client.request("set_rotation_stage", **angles).items()}
        except ServiceUnavailable as error:
            raise LinkError(f"the rotation stage (fake lab) does not answer: {error}") from None
        except CommandError as error:
            raise DeviceError(f"the rotation stage refused: {error.message}") from None

    def travel(self) -> dict[str, tuple[float, float]]:
        return dict(ROTATION_STAGE_LIMITS_DEG)

    def read_angles(self) -> dict[str, float]:
        return self._request()

    def move_to(self, angles: dict[str, float]) -> dict[str, float]:
        return self._request(**angles)

    def halt(self) -> None:
        """The simulated stage reaches each target at once: nothing is ever in motion."""

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

    def halt(self) -> None:
        """Every target is reached at once: nothing is ever in motion."""

    def close(self) -> None:
        """Nothing to close."""
