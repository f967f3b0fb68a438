"""Small helpers for the words the services, the CLI and the reports say to people."""

from __future__ import annotations


def counted(number: int, noun: str, plural: str | None = None) -> str:
    """``number`` and ``noun``, plural unless one: ``counted(1, "wide sweep")`` is
    "1 wide sweep", ``counted(3, "wide sweep")`` "3 wide sweeps"."""
    return f"{number} {noun if number == 1 else plural or noun + 's'}"


def tilt_teach_progress(teach) -> str:
    """Which of a teach's focus sweeps is scanning and how well the ones before pinned the
    tilts, in words (``teach``: a :class:`semservo.api.TiltTeach` or the estimator's own);
    the fine sweeps counted on their own, after the wide ones."""
    measure = "" if teach.focus_measure == "normalized_variance" else f"read by the {teach.focus_measure} measure"
    if teach.fine:
        wide = teach.wide_sweeps
        notes = [f"of at most {teach.max_sweeps - wide}", f"after {counted(wide, 'wide one')}"]
        which = f"fine focus sweep {teach.sweep - wide}"
    else:
        notes = [f"of at most {teach.max_sweeps}"] if teach.max_sweeps > 1 else []
        which = f"focus sweep {teach.sweep}" if teach.max_sweeps > 1 else "focus sweep"
    notes += [measure] if measure else []
    text = which + (f" ({', '.join(notes)})" if notes else "")
    if teach.pinned_deg:
        text += f"; the sweeps so far pin the tilts to +-{teach.pinned_deg[0]:.3f} and +-{teach.pinned_deg[1]:.3f} deg"
    return text


def taught_sweeps(tilt: dict) -> str:
    """What a reference's tilts were taught from (its ``tilt`` detail), in words: "7 fine
    focus sweeps of 19 frames pooled (after 1 wide one could not pin the tilts)"."""
    sweeps, fine = tilt.get("sweeps", 1), bool(tilt.get("fine"))
    text = f"{counted(sweeps, 'fine focus sweep' if fine else 'focus sweep')} of {tilt.get('frames')} frames"
    text += " pooled" if sweeps > 1 else ""
    if fine and tilt.get("wide_sweeps"):
        text += f" (after {counted(tilt['wide_sweeps']['sweeps'], 'wide one')} could not pin the tilts)"
    return text
