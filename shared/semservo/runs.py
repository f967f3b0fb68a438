"""Reading a finished run's record (the controller's ``records``, the gateway's
``trajectory``): where its stage came to rest.

The truth of a run on the fake lab is the true pose over the scans of the frames it
ended on. Not over its last frames whatever they were: the frame a move was made from
was scanned before that move, so a window over it straddles the move and reads a mix of
two poses (a test read 0.40 px from a stage resting within 0.05). Not read later either:
creep of the last large move goes on (1.5 % of it per decade of time), and at the fake
lab's 20x speed a busy machine's seconds are decades.
"""

from __future__ import annotations

from typing import Sequence


def resting_frames(records: Sequence[dict]) -> list[dict]:
    """The records of the frames scanned while the stage rested after the run's last move
    (of x, y or the tilts), those not held (a frame scanned during the move is held as
    stale); the last frame's record when there are none. Only records of frames (with a
    ``frame_source_interval_s``)."""
    last_move = max((index for index, record in enumerate(records)
                     if record.get("action") == "moved" or record.get("tilt_action") == "moved"), default=-1)
    resting = [record for record in records[last_move + 1:] if record.get("frame_source_interval_s")
               and not str(record.get("action", "")).startswith("held")]
    return resting or [record for record in records[-1:] if record.get("frame_source_interval_s")]


def resting_interval(records: Sequence[dict]) -> tuple[float, float] | None:
    """The simulated interval over which the run's stage rested (:func:`resting_frames`):
    from the first resting frame's scan to the last's; None without a frame."""
    resting = resting_frames(records)
    if not resting:
        return None
    return resting[0]["frame_source_interval_s"][0], resting[-1]["frame_source_interval_s"][1]
