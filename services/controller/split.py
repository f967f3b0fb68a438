"""The beam and the stage: which axes make a planar move.

A stage whose driver works in physical units may have a beam shift beside it (``state``'s
``axes``: ``beam_x``, ``beam_y``, ``moves: beam``), which moves the content as ``x``, ``y``
do (:class:`semservo.instruments.Axis`) over a small travel, with no mechanics: no
backlash, no settling, no wear. A run's ``beam_shift_within_um`` (a
:class:`~semservo.protocol.controller.RunSettings` field) splits the work: once the
error (the distance to the target, as the frame measures it) is at most that many
micrometres, the beam makes the moves, while it has room for them; farther, or when the
beam has no room left, the stage does. So the stage makes the long approach and the
beam the last micrometres, and a run that holds (``hold``) corrects drift with the beam
until it nears the end of its travel, then with the stage. 0 (the default): the
stage makes every move, as on an amplifier (whose driver has no beam axes).
"""

from __future__ import annotations

from dataclasses import dataclass

#: The beam keeps this fraction of its travel in reserve at each end: a move that would
#: use it goes to the stage (a beam shift near its limit is where the SDK clips).
BEAM_MARGIN = 0.05

#: A planar axis and the beam axis that moves the content the same way.
BEAM_AXIS = {"x": "beam_x", "y": "beam_y"}


@dataclass
class BeamAxes:
    """The stage's beam shift as the run knows it: each axis's travel and where it is
    (followed from every move's reply)."""

    travel: dict[str, tuple[float, float]]
    position: dict[str, float]

    @classmethod
    def of(cls, stage_state) -> "BeamAxes | None":
        """From the stage's ``state`` (a :class:`~semservo.protocol.stage.StageState`);
        None when its driver has no beam axes (an amplifier, a stage alone)."""
        axes = getattr(stage_state, "axes", None) or {}
        beam = {name: axes[name] for name in BEAM_AXIS.values() if name in axes and axes[name].moves == "beam"}
        if getattr(stage_state, "kind", "voltage") != "physical" or len(beam) != len(BEAM_AXIS):
            return None
        return cls({name: (axis.travel[0], axis.travel[1]) for name, axis in beam.items()},
                   {name: axis.position or 0.0 for name, axis in beam.items()})

    def has_room(self, targets: dict[str, float]) -> bool:
        """Whether the beam can make this planar move and keep its margin."""
        for axis, step in targets.items():
            low, high = self.travel[BEAM_AXIS[axis]]
            reserve = BEAM_MARGIN * (high - low)
            if not low + reserve <= self.position[BEAM_AXIS[axis]] + step <= high - reserve:
                return False
        return True

    def follow(self, positions_um: dict[str, float]) -> None:
        """Where the beam is after a move (the stage service's reply)."""
        self.position.update({name: positions_um[name] for name in self.position if name in positions_um})


def split(targets: dict[str, float], beam: BeamAxes | None, within_um: float,
          error_um: float | None) -> dict[str, float]:
    """The axes that make the planar move ``targets`` (um, ``x``, ``y``, relative): the
    beam's (``beam_x``, ``beam_y``) when the error ``error_um`` is at most ``within_um``
    and the beam has room for the move, else the stage's. Pure apart from reading ``beam``."""
    if beam is None or within_um <= 0 or not targets or error_um is None:
        return dict(targets)
    if not (error_um <= within_um and beam.has_room(targets)):
        return dict(targets)
    return {BEAM_AXIS[axis]: step for axis, step in targets.items()}
