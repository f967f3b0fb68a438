"""The beam and the stage: which axes make a run's planar move (services.controller.split)."""

from __future__ import annotations

from semservo.protocol.stage import AxisState, StageState
from services.controller.split import BeamAxes, split


def state(kind: str = "physical", beam: bool = True) -> StageState:
    axes = {"x": AxisState(unit="um", moves="stage", position=0.0, travel=[-50.0, 50.0], max_step=10.0),
            "y": AxisState(unit="um", moves="stage", position=0.0, travel=[-50.0, 50.0], max_step=10.0)}
    if beam:
        axes |= {name: AxisState(unit="um", moves="beam", position=1.0, travel=[-5.0, 5.0], max_step=10.0)
                 for name in ("beam_x", "beam_y")}
    limits = {"voltage_min": 0, "voltage_max": 0, "travel_min_um": 0, "travel_max_um": 0, "max_step_v": 1,
              "max_rate_v_per_s": 1, "max_turn_deg": 1, "device_voltage": []}
    return StageState(url="u", link="connected", state="ready", reason="", device=None, voltages={},
                      positions_um={}, limits=limits, watchdog={"armed": False, "timeout_s": 0, "owner": None},
                      models={}, rotation=None, kind=kind, axes=axes, last_error=None, moves=0, turns=0, refused=0,
                      link_lost=0, reconnects=0, uncommanded_changes=0)


def test_the_beam_axes_are_found_on_a_physical_driver_only():
    beam = BeamAxes.of(state())
    assert beam.travel == {"beam_x": (-5.0, 5.0), "beam_y": (-5.0, 5.0)} and beam.position["beam_x"] == 1.0
    assert BeamAxes.of(state(beam=False)) is None and BeamAxes.of(state(kind="voltage")) is None


def test_far_from_the_target_the_stage_moves_near_it_the_beam_while_it_has_room():
    beam = BeamAxes.of(state())
    move = {"x": 0.4, "y": -0.2}
    assert split(move, beam, 2.0, error_um=8.0) == move  # the approach: the stage
    assert split(move, beam, 2.0, error_um=1.5) == {"beam_x": 0.4, "beam_y": -0.2}  # the last micrometres
    assert split(move, beam, 0.0, error_um=0.5) == move  # 0: the stage makes every move
    assert split(move, None, 2.0, error_um=0.5) == move and split(move, beam, 2.0, error_um=None) == move
    beam.follow({"beam_x": 4.5, "beam_y": 0.0, "x": 3.0})  # near the end of its travel (a 5 % margin)
    assert beam.position == {"beam_x": 4.5, "beam_y": 0.0}
    assert split(move, beam, 2.0, error_um=1.0) == move  # no room: the stage
    assert split({"x": -0.4}, beam, 2.0, error_um=1.0) == {"beam_x": -0.4}  # back towards the centre: room
