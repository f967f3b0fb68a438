"""Units and signs between semservo and OpenFIBSEM, in one place.

semservo moves in **micrometres in the image plane**, by how far the image's content
moves, x to the right and y down as displayed (:mod:`semservo.estimation`'s convention,
the controller's camera-to-stage transform); a beam axis moves the content the way the
stage axis of the same letter does (:class:`semservo.instruments.Axis`). OpenFIBSEM
works in **metres** (radians for the stage's r and t), and its two image-plane motions
are ``stable_move(dx, dy, beam_type)`` (the stage, y corrected for the pre-tilt and tilt:
the stage's y and z move together) and ``beam_shift(dx, dy, beam_type)``.

Their signs are OpenFIBSEM's own, as its alignment uses them on Thermo Fisher and TESCAN
microscopes (``fibsem.alignment``, 0.5.3): it measures the content's displacement
(dx to the right, dy down, ``shift_from_crosscorrelation``) and corrects it with
``stable_move(dx, -dy)`` or with ``beam_shift(-dx, dy)`` (``_apply_shift``). So
``stable_move(a, b)`` moves the content by (-a, +b), and ``beam_shift(a, b)`` by (+a, -b):
to move it by semservo's (x, y), ``stable_move(-x, y)`` (:data:`STAGE_SIGNS`) or
``beam_shift(x, -y)`` (:data:`BEAM_SIGNS`). A microscope whose scan is rotated or
mirrored shows it in the jog check of ``docs/instruments.md``; set it with
``SEMSERVO_CONTROLLER__AXIS_SIGNS`` (both paths), or per driver with the URL's
``stage_signs`` / ``beam_signs``.
"""

from __future__ import annotations

import math

#: Metres in a micrometre.
METRES_PER_UM = 1e-6

#: semservo's stage x, y (um the content moves, x right, y down) -> ``stable_move``'s dx, dy.
STAGE_SIGNS: tuple[int, int] = (-1, 1)
#: semservo's beam_x, beam_y (um the content moves, as for the stage) -> ``beam_shift``'s dx, dy.
BEAM_SIGNS: tuple[int, int] = (1, -1)


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
