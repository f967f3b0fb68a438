"""Where a finished run's stage rested (semservo.runs): the frames after its last move,
not the frame the move was made from nor those scanned during it."""

from __future__ import annotations

from semservo.runs import resting_frames, resting_interval


def frame(action: str, start: float, **extra) -> dict:
    return {"action": action, "frame_source_interval_s": (start, start + 0.4), **extra}


def test_the_stage_rests_over_the_frames_after_its_last_move():
    records = [frame("moved", 0.0), frame("held: stale (scanned during the last move)", 0.5),
               frame("moved", 1.0), frame("held: stale (scanned during the last move)", 1.5),
               frame("within tolerance", 2.0), frame("within tolerance", 2.5)]
    assert resting_frames(records) == records[4:]
    assert resting_interval(records) == (2.0, 2.9)  # not from 1.0: that frame was scanned before the move


def test_a_tilt_move_counts_as_a_move_and_records_without_a_frame_are_left_out():
    records = [frame("within tolerance", 0.0), {"action": "moved", "tilt_action": "moved"},
               frame("within tolerance", 1.0, tilt_action="moved"), {"action": "stopped"},
               frame("within tolerance", 2.0)]
    assert resting_frames(records) == [records[4]]
    assert resting_interval(records) == (2.0, 2.4)


def test_without_a_resting_frame_the_last_frame_stands_and_without_frames_none():
    records = [frame("within tolerance", 0.0), frame("moved", 1.0)]
    assert resting_frames(records) == [records[1]]
    assert resting_interval([{"action": "stopped"}]) is None
