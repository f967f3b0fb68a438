"""How a teach's focus sweeps are said, in the CLI, the demo and the estimator's log: the
fine sweeps counted on their own after the wide ones (a fresh-clone review saw "fine focus
sweep 8 (of at most 9)" for the 7th fine sweep of at most 8, and "1 wide focus sweeps")."""

from __future__ import annotations

from semservo.api import TiltTeach
from semservo.wording import counted, taught_sweeps, tilt_teach_progress


def test_counted_says_one_thing_and_many():
    assert counted(1, "wide one") == "1 wide one" and counted(3, "wide one") == "3 wide ones"
    assert counted(0, "sweep") == "0 sweeps" and counted(2, "focus sweep") == "2 focus sweeps"
    assert counted(2, "kernel in focus", "kernels in focus") == "2 kernels in focus"


def test_the_fine_sweeps_are_counted_on_their_own_after_the_wide_ones():
    wide = TiltTeach(state="sweeping", reference_id="r1", sweep=2, max_sweeps=4, pinned_deg=[0.15, 0.2])
    assert tilt_teach_progress(wide) == ("focus sweep 2 (of at most 4); the sweeps so far pin the tilts to +-0.150 "
                                         "and +-0.200 deg")
    fine = TiltTeach(state="sweeping", reference_id="r1", sweep=8, max_sweeps=9, fine=True, wide_sweeps=1,
                     focus_measure="gradient")
    assert tilt_teach_progress(fine) == ("fine focus sweep 7 (of at most 8, after 1 wide one, read by the gradient "
                                         "measure)")
    single = TiltTeach(state="sweeping", reference_id="r1", sweep=1, max_sweeps=1)
    assert tilt_teach_progress(single) == "focus sweep"


def test_what_a_teach_was_taught_from_names_its_fine_and_wide_sweeps():
    assert taught_sweeps({"sweeps": 1, "frames": 21}) == "1 focus sweep of 21 frames"
    assert taught_sweeps({"sweeps": 3, "frames": 21}) == "3 focus sweeps of 21 frames pooled"
    fine = {"sweeps": 7, "frames": 19, "fine": True, "wide_sweeps": {"sweeps": 1}}
    assert taught_sweeps(fine) == ("7 fine focus sweeps of 19 frames pooled (after 1 wide one could not pin the "
                                   "tilts)")
    assert taught_sweeps({**fine, "sweeps": 1, "wide_sweeps": {"sweeps": 2}}) == (
        "1 fine focus sweep of 19 frames (after 2 wide ones could not pin the tilts)")
