"""Units and signs between semservo and OpenFIBSEM, in one place.

semservo moves in **micrometres in the image plane**, x to the right and y down as the
image is displayed (:mod:`semservo.estimation`'s convention, the controller's
camera-to-stage transform), and a beam axis moves the content the way the stage axis of
the same letter does (:class:`semservo.instruments.Axis`). OpenFIBSEM works in **metres**
(and radians for the stage's r and t), with the image's y pointing **up**:

* ``stable_move(dx, dy, beam_type)`` moves the stage so that the view moves by (dx, dy)
  in the image plane, y up (fibsem corrects y for the shuttle's pre-tilt and the stage's
  tilt: the stage's y and z move together);
* ``beam_shift(dx, dy, beam_type)`` shifts the scanned field: the content moves the
  other way than for a stage move. fibsem's own alignment corrects one measured shift
  with ``stable_move(dx, -dy)`` or with ``beam_shift(-dx, dy)``
  (``fibsem.alignment._apply_shift``, 0.5.3): opposite signs on both axes.

So, for a content motion in semservo's axes: the stage's x is fibsem's x and its y is
fibsem's -y (:data:`STAGE_SIGNS`); the beam shift's x is fibsem's -x and its y fibsem's y
(:data:`BEAM_SIGNS`). A microscope whose scan is rotated or mirrored shows it in the jog
check of ``docs/instruments.md`` and is set with ``SEMSERVO_CONTROLLER__AXIS_SIGNS`` (and
these signs, per driver, with the URL's ``stage_signs`` / ``beam_signs``).
"""

from __future__ import annotations

import math

#: Metres in a micrometre.
METRES_PER_UM = 1e-6

#: semservo's stage x, y (um, image plane, y down) -> ``stable_move``'s dx, dy (y up).
STAGE_SIGNS: tuple[int, int] = (1, -1)
#: semservo's beam_x, beam_y (um, the content's motion as for the stage) -> ``beam_shift``'s dx, dy.
BEAM_SIGNS: tuple[int, int] = (-1, 1)


def _checked(value: float, what: str) -> float:
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"{what} must be a finite number, got {value!r}")
    return number


def to_metres(x_um: float, y_um: float, signs: tuple[int, int]) -> tuple[float, float]:
    """fibsem's (dx, dy) in metres for semservo's displacement (x, y) in micrometres."""
    # + 0.0: a zero is +0 whatever its sign (the command log reads "dy=0", not "dy=-0").
    return (signs[0] * _checked(x_um, "x") * METRES_PER_UM + 0.0, signs[1] * _checked(y_um, "y") * METRES_PER_UM + 0.0)


def to_micrometres(x_m: float, y_m: float, signs: tuple[int, int]) -> tuple[float, float]:
    """semservo's (x, y) in micrometres for fibsem's (x, y) in metres: the inverse of
    :func:`to_metres` (a sign is its own inverse)."""
    return (signs[0] * float(x_m) / METRES_PER_UM + 0.0, signs[1] * float(y_m) / METRES_PER_UM + 0.0)


def stage_move_m(x_um: float, y_um: float, signs: tuple[int, int] = STAGE_SIGNS) -> tuple[float, float]:
    """``stable_move``'s (dx, dy) in metres that moves the content by (x, y) um as
    semservo's stage axes do."""
    return to_metres(x_um, y_um, signs)


def beam_shift_m(x_um: float, y_um: float, signs: tuple[int, int] = BEAM_SIGNS) -> tuple[float, float]:
    """``beam_shift``'s (dx, dy) in metres that moves the content as semservo's stage
    axes moving by (x, y) um do."""
    return to_metres(x_um, y_um, signs)


def signs_from_text(text: str | None, default: tuple[int, int]) -> tuple[int, int]:
    """``"1,-1"`` as (1, -1); None: ``default``. Anything but two signs is refused."""
    if text is None:
        return default
    try:
        signs = tuple(int(part) for part in str(text).split(","))
    except ValueError:
        signs = ()
    if len(signs) != 2 or any(sign not in (-1, 1) for sign in signs):
        raise ValueError(f"signs are two of +1 or -1 separated by a comma (e.g. '1,-1'), got {text!r}")
    return signs  # type: ignore[return-value]
