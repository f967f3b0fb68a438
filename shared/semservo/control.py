"""The Fourier-based visual servoing law (paper section II-E, eq. 30-37): small pure
functions from a motion estimate to a stage displacement, shared by the controller
service, the calibration routine, the positioning benchmark and lab scripts.

Units: translation errors are in pixels of the current image, the rotation error in
radians (theta-u, eq. 30); velocities in the same units per second; displacements of
the stage in micrometres (x, y) and degrees (rotation about the beam).

Sign conventions, written down once:

* The error is the motion estimate itself, e = s - s* with s* = 0 (eq. 31): the content
  displacement of the current image against the taught one (x right, y down, rotation
  counter-clockwise as displayed; :mod:`semservo.estimation`).
* The law drives e to zero: v = -lambda (H + diag H)^-1 L^T e (eq. 36). A stage move
  that shifts the content by +1 px changes e by +1 px, so the stage must move the
  content by -e: the camera-to-stage transform (:class:`CameraToStage`) maps a content
  motion in pixels to the stage motion that causes it.
* theta-u (eq. 34): we use the interaction matrix of ViSP's ``vpFeatureThetaU`` for the
  ``cdRc`` representation, L_w = I + (theta/2)[u]x + (1 - sinc theta / sinc^2(theta/2))[u]x^2.
  The paper prints the middle term with a minus sign, which is ViSP's form for the
  inverse rotation (``cRcd``) up to the overall sign. With rotation about the beam only
  (u = z) the two agree: the z-z entry is 1 either way, and the sign choice matters only
  once the tilts are servoed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from semservo.estimation.raster import PARTIAL_FRAME_FROM

#: Degrees of freedom this law can drive, in the order of the error vector.
DEGREES_OF_FREEDOM = ("x", "y", "rotation")


# --------------------------------------------------------------------------------------
# Features and error (eq. 30-32)


def error_vector(dx_px: float, dy_px: float, rotation_deg: float, dofs: Sequence[str]) -> np.ndarray:
    """e = s - s* (eq. 31) for the chosen degrees of freedom: translation in pixels,
    the rotation feature u theta about the beam (u = z) in radians."""
    values = {"x": dx_px, "y": dy_px, "rotation": math.radians(rotation_deg)}
    unknown = set(dofs) - set(values)
    if unknown:
        raise ValueError(f"unknown degrees of freedom {sorted(unknown)}; known: {', '.join(DEGREES_OF_FREEDOM)}")
    return np.array([values[dof] for dof in dofs], dtype=float)


def cost(error: np.ndarray) -> float:
    """C = e^T e (eq. 32)."""
    return float(error @ error)


# --------------------------------------------------------------------------------------
# Interaction matrix (eq. 33-34)


def skew(vector: Sequence[float]) -> np.ndarray:
    """[u]x, the cross-product matrix."""
    x, y, z = vector
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def theta_u_interaction(theta: float, axis: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """L_w for the theta-u rotation feature (eq. 34), in ViSP's ``cdRc`` form:
    I + (theta/2)[u]x + (1 - sinc(theta) / sinc^2(theta/2)) [u]x^2.
    Singular only at theta = 2 pi, as the paper notes."""
    u = np.asarray(axis, dtype=float)
    norm = np.linalg.norm(u)
    if norm == 0:
        raise ValueError("the rotation axis u must not be zero")
    ux = skew(u / norm)
    sinc = np.sinc(theta / np.pi)  # numpy's sinc is sin(pi x)/(pi x)
    half_sinc = np.sinc(theta / (2 * np.pi))
    return np.eye(3) + theta / 2 * ux + (1 - sinc / half_sinc**2) * ux @ ux


def interaction_matrix(dofs: Sequence[str], theta: float = 0.0) -> np.ndarray:
    """The decoupled L_f (eq. 33): L_v = I for translation, the z-z entry of L_w for
    rotation about the beam, zeros between them."""
    size = len(dofs)
    matrix = np.eye(size)
    if "rotation" in dofs:
        index = list(dofs).index("rotation")
        matrix[index, index] = theta_u_interaction(theta)[2, 2]
    return matrix


# --------------------------------------------------------------------------------------
# Gains (eq. 35)


@dataclass(frozen=True)
class AdaptiveGain:
    """lambda_a = sigma_e / Lambda (eq. 35), clipped to [minimum, maximum] (per second).

    sigma_e is read as the root-mean-square of the error components (the spread of the
    error about zero, its target): a variance about the error's own mean would vanish
    whenever the components are equal, e.g. a diagonal offset, and stop the stage. The
    gain grows with the error, so the stage moves fast when far and slows near the
    target; the floor keeps the last pixels from taking forever.

    Why these defaults: with L = I the law and eq. 37 give e_k+1 = (1 - a) e_k - a e_k-1
    with a = lambda T / 4 (T the sampling time), which approaches without overshoot
    (real roots) for a <= 3 - 2 sqrt(2) = 0.17. The paper's SEM gives T = 0.65-0.9 s
    (a fresh frame every second scan), so lambda <= 0.8 per second.
    """

    scale: float = 50.0  # Lambda, in error units x seconds
    minimum: float = 0.5
    maximum: float = 0.8

    def __call__(self, error: np.ndarray) -> float:
        sigma = float(np.sqrt(np.mean(error**2))) if error.size else 0.0
        return float(np.clip(sigma / self.scale, self.minimum, self.maximum))


@dataclass(frozen=True)
class ExponentialGain:
    """The usual visual-servoing adaptive gain (as ViSP's ``vpAdaptiveGain``):
    lambda(x) = (l0 - l_inf) exp(-slope0 x / (l0 - l_inf)) + l_inf with x = ||e||_inf;
    l0 near zero error, l_inf far away, slope0 the slope at zero."""

    at_zero: float = 0.8
    at_infinity: float = 0.5
    slope_at_zero: float = 0.02

    def __call__(self, error: np.ndarray) -> float:
        x = float(np.max(np.abs(error))) if error.size else 0.0
        span = self.at_zero - self.at_infinity
        if span <= 0:
            return self.at_infinity
        return span * math.exp(-self.slope_at_zero * x / span) + self.at_infinity


# --------------------------------------------------------------------------------------
# The law (eq. 36) and the displacement (eq. 37)


def levenberg_marquardt_velocity(error: np.ndarray, interaction: np.ndarray, gain: float) -> np.ndarray:
    """v = -lambda_a (H + diag(H))^-1 L^T e, H = L^T L (eq. 36), in the camera frame
    (the camera-to-stage transform is applied by :class:`CameraToStage`)."""
    hessian = interaction.T @ interaction
    damped = hessian + np.diag(np.diag(hessian))
    return -gain * np.linalg.solve(damped, interaction.T @ error)


def displacement(previous_velocity: np.ndarray, velocity: np.ndarray, sampling_time_s: float) -> np.ndarray:
    """d = v_avg t with v_avg = (v0 + v_cur) / 2 (eq. 37): v0 the velocity commanded at
    the previous iteration, t the measured time between the two iterations."""
    if sampling_time_s < 0:
        raise ValueError(f"sampling time must not be negative, got {sampling_time_s}")
    return (previous_velocity + velocity) / 2 * sampling_time_s


@dataclass(frozen=True)
class CameraToStage:
    """^cV_p of eq. 36: how a stage move shows in the image, for every axis the laws drive.

    ``axis_signs``: +1 when moving the stage axis forward moves the content towards +x
    (right) / +y (down) of the image. ``orientation_deg``: the stage x axis seen in the
    image, counter-clockwise as displayed from the image's x axis. The pixel size comes
    with each frame (P = D / G, eq. 43), so a change of magnification needs nothing here.
    ``rotation_sign``: +1 when a positive turn of the rotation stage turns the content
    counter-clockwise. ``tilt_signs``: +1 when a positive stage tilt tilts the surface by
    +alpha / +beta (:mod:`semservo.estimation.tilt`'s convention).
    """

    axis_signs: tuple[int, int] = (1, 1)
    orientation_deg: float = 0.0
    rotation_sign: int = 1
    tilt_signs: tuple[int, int] = (1, 1)

    def stage_move_um(self, content_dx_px: float, content_dy_px: float, pixel_size_nm: float) -> tuple[float, float]:
        """The stage move (um, stage axes) that moves the content by (dx, dy) px."""
        scale = pixel_size_nm / 1000.0
        theta = math.radians(self.orientation_deg)
        # Content moves (cos, -sin) for a stage x move: y is down, angles counter-clockwise.
        image = np.array([content_dx_px, content_dy_px]) * scale
        to_image = np.array([[math.cos(theta), math.sin(theta)], [-math.sin(theta), math.cos(theta)]])
        stage = np.linalg.solve(to_image, image)
        return float(stage[0] * self.axis_signs[0]), float(stage[1] * self.axis_signs[1])

    def content_move_px(self, stage_dx_um: float, stage_dy_um: float, pixel_size_nm: float) -> tuple[float, float]:
        """Inverse of :meth:`stage_move_um`."""
        theta = math.radians(self.orientation_deg)
        to_image = np.array([[math.cos(theta), math.sin(theta)], [-math.sin(theta), math.cos(theta)]])
        stage = np.array([stage_dx_um * self.axis_signs[0], stage_dy_um * self.axis_signs[1]])
        image = to_image @ stage / (pixel_size_nm / 1000.0)
        return float(image[0]), float(image[1])

    def stage_move(self, content: dict[str, float], pixel_size_nm: float | None = None) -> dict[str, float]:
        """The stage displacement, by stage axis, that moves the content by ``content``:
        "x", "y" in pixels (needs the pixel size), "rotation", "alpha", "beta" in
        radians. Keys of the result: "x_um", "y_um", "rotation_deg", "tilt_x_deg",
        "tilt_y_deg", each only for a degree of freedom in ``content``."""
        move = {}
        if "x" in content or "y" in content:
            if pixel_size_nm is None:
                raise ValueError("a translation needs the pixel size")
            x_um, y_um = self.stage_move_um(content.get("x", 0.0), content.get("y", 0.0), pixel_size_nm)
            if "x" in content:
                move["x_um"] = x_um
            if "y" in content:
                move["y_um"] = y_um
        if "rotation" in content:
            move["rotation_deg"] = math.degrees(content["rotation"]) * self.rotation_sign
        if "alpha" in content:
            move["tilt_x_deg"] = math.degrees(content["alpha"]) * self.tilt_signs[0]
        if "beta" in content:
            move["tilt_y_deg"] = math.degrees(content["beta"]) * self.tilt_signs[1]
        return move


#: lambda T for which e_k+1 = (1 - a) e_k - a e_k-1, a = lambda T / 4, still approaches
#: without overshoot: a = 3 - 2 sqrt(2) (see AdaptiveGain).
NO_OVERSHOOT_GAIN_TIMES_T = 4 * (3 - 2 * math.sqrt(2))


@dataclass(frozen=True)
class LawStep:
    """What one iteration of a law computed: the same record for every law
    (:class:`ControlLaw`, :class:`TiltLaw`, :class:`PositionLaw`)."""

    error: tuple[float, ...]  # e = s - s* (eq. 31) in the law's units (px, rad)
    cost: float  # C = e^T e (eq. 32)
    gain: float  # lambda (eq. 35), after the no-overshoot cap
    velocity: tuple[float, ...]  # eq. 36
    move: dict[str, float]  # stage displacement by axis: "x_um", "y_um", "rotation_deg", "tilt_x_deg", "tilt_y_deg"
    integral: tuple[float, ...] | None = None
    #: Why nothing moves, when the law says (recorded as the iteration's action).
    held: str = ""

    @classmethod
    def idle(cls) -> "LawStep":
        """Nothing to do (e.g. a tilts-only run between two focus sweeps)."""
        return cls(error=(), cost=0.0, gain=0.0, velocity=(), move={})


def velocity_and_displacement(error: np.ndarray, interaction: np.ndarray, gain: float, sampling_time_s: float,
                              previous_velocity: np.ndarray | None, previous_gain: float | None = None
                              ) -> tuple[float, np.ndarray, np.ndarray]:
    """The sequence both of the paper's laws share: the gain capped for the sampling
    time, the velocity (eq. 36) and the displacement over the sampling time (eq. 37,
    from the previous velocity, or the current one on the first iteration).

    Eq. 37 scales the move with the sampling time, so a slow image source (or a
    sped-up simulation that renders slower than it scans) would overshoot: the gain is
    capped where the loop stops approaching monotonically. ``previous_gain``: the gain
    the previous velocity was commanded at; given, and above this one (capped for a
    longer interval, or a smaller error), the previous velocity is scaled to this gain,
    so that eq. 37 does not carry a velocity capped for a short interval over a long one
    and the bound holds whatever the intervals (a move only gets smaller for it; the
    tilts' sweeps come unevenly). Returns (gain, velocity, displacement)."""
    gain = min(gain, NO_OVERSHOOT_GAIN_TIMES_T / max(sampling_time_s, 1e-6))
    velocity = levenberg_marquardt_velocity(error, interaction, gain)
    previous = previous_velocity if previous_velocity is not None else velocity
    if previous_velocity is not None and previous_gain and gain < previous_gain:
        previous = previous_velocity * (gain / previous_gain)
    return gain, velocity, displacement(previous, velocity, sampling_time_s)


def _floats(values) -> tuple[float, ...]:
    return tuple(float(value) for value in values)


@dataclass
class ControlLaw:
    """One iteration of the paper's controller, with the state it needs between
    iterations (the previous velocity, for eq. 37). No sockets, no clocks: the caller
    passes the measured sampling time."""

    dofs: tuple[str, ...] = ("x", "y")
    gain: AdaptiveGain | ExponentialGain = field(default_factory=AdaptiveGain)
    camera_to_stage: CameraToStage = field(default_factory=CameraToStage)
    previous_velocity: np.ndarray | None = None
    #: Integral action (not in the paper): the law sees e + (1/T_i) sum(e T). None keeps
    #: the paper's purely proportional law. A proportional law leaves a steady error of
    #: drift / gain: at x5000 thermal drift of 1.5-2 nm/s is 0.05 px/s, and the loop,
    #: whose gain is capped near 0.5 /s by the slow frames, then rests ~0.3 px off.
    integral_time_s: float | None = None
    #: The integral only accumulates while the error is under this (px, or degrees for
    #: rotation), so the approach from far away does not wind it up.
    integral_zone: float = 2.0
    integral: np.ndarray | None = None
    #: Whether the run has converged is the caller's rule for this law (the mean error of
    #: the last N fresh frames); :attr:`PositionLaw.converged` is the position law's own.
    converged = None

    def reset(self) -> None:
        self.previous_velocity = None
        self.integral = None

    def applied(self, move: dict[str, float] | None, at_s: float | None = None) -> None:
        """The move as the stage carried it out: nothing to learn for this law (the same
        call as :meth:`PositionLaw.applied`, so a caller treats every law alike)."""

    def view_moved(self) -> None:
        """The view moved by design (a tilt about a pivot below the surface): nothing to
        forget for this law, which acts on each frame's error alone (the same call as
        :meth:`PositionLaw.view_moved`)."""

    def _with_integral(self, error: np.ndarray, sampling_time_s: float) -> np.ndarray:
        if not self.integral_time_s:
            return error
        if self.integral is None:
            self.integral = np.zeros_like(error)
        if float(np.abs(error).max()) < self.integral_zone:
            self.integral = self.integral + error * sampling_time_s
            # Anti-windup: the integral term never asks for more than the zone.
            self.integral = np.clip(self.integral, -self.integral_zone * self.integral_time_s,
                                    self.integral_zone * self.integral_time_s)
        return error + self.integral / self.integral_time_s

    def step(self, dx_px: float, dy_px: float, rotation_deg: float, pixel_size_nm: float,
             sampling_time_s: float, *, fresh: bool = True, confident: bool = True,
             frame_interval_s: tuple[float, float] | None = None, now_s: float | None = None,
             scan_time_s: float | None = None) -> LawStep:
        """Error, cost, gain, camera velocity (eq. 30-36) and the stage displacement
        (eq. 37): ``move`` has "x_um", "y_um", "rotation_deg" for the chosen DOFs. The
        keywords are :meth:`PositionLaw.step`'s, so a caller treats both laws alike: a
        frame not ``fresh`` or not ``confident`` is not acted on; the times are unused."""
        if not fresh or not confident:
            return LawStep.idle()
        error = error_vector(dx_px, dy_px, rotation_deg, self.dofs)
        theta = math.radians(rotation_deg) if "rotation" in self.dofs else 0.0
        gain, velocity, moved = velocity_and_displacement(
            self._with_integral(error, sampling_time_s), interaction_matrix(self.dofs, theta), self.gain(error),
            sampling_time_s, self.previous_velocity)
        self.previous_velocity = velocity
        move = self.camera_to_stage.stage_move(dict(zip(self.dofs, moved)), pixel_size_nm)
        return LawStep(_floats(error), cost(error), gain, _floats(velocity), move,
                       None if self.integral is None else _floats(self.integral))


# --------------------------------------------------------------------------------------
# The tilts: the theta-u rotation feature (eq. 30, 34) for alpha and beta

#: The out-of-plane degrees of freedom, measured from focus sweeps (alpha about the
#: image's x axis, beta about its y axis; :mod:`semservo.estimation.tilt`'s convention).
TILT_DEGREES_OF_FREEDOM = ("alpha", "beta")


def theta_u(rotation: np.ndarray) -> np.ndarray:
    """The rotation vector theta u of a rotation matrix (the feature of eq. 30)."""
    cosine = np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0)
    theta = math.acos(cosine)
    if theta < 1e-12:
        return np.zeros(3)
    axis = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0], rotation[1, 0] - rotation[0, 1]])
    return theta * axis / (2 * math.sin(theta))


def tilt_error(alpha_deg: float, beta_deg: float, dofs: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """The tilt error as the theta-u vector of the rotation R_x(alpha) R_y(beta) between
    the current and the taught surface (eq. 30), its components for ``dofs`` (rad), and
    their interaction matrix, the x-y block of L_w (eq. 34)."""
    from semservo.estimation.tilt import tilt_rotation  # the convention lives there

    unknown = set(dofs) - set(TILT_DEGREES_OF_FREEDOM)
    if unknown:
        raise ValueError(f"unknown tilt degrees of freedom {sorted(unknown)}")
    vector = theta_u(tilt_rotation(alpha_deg if "alpha" in dofs else 0.0, beta_deg if "beta" in dofs else 0.0))
    theta = float(np.linalg.norm(vector))
    full = theta_u_interaction(theta, vector if theta > 0 else (1.0, 0.0, 0.0))
    index = [TILT_DEGREES_OF_FREEDOM.index(dof) for dof in dofs]
    return vector[index], full[np.ix_(index, index)]


@dataclass
class TiltLaw:
    """The law of eq. 36-37 for the tilts: the error is the theta-u vector of the tilt
    rotation R_x(alpha) R_y(beta) between the current and the taught surface (eq. 30),
    its interaction matrix the x-y block of L_w (eq. 34), damped as eq. 36. It runs at
    the rate of the focus sweeps, with the time between two sweeps as its sampling time,
    and keeps its own previous velocity for eq. 37. The tilt signs come from the
    camera-to-stage transform (:attr:`CameraToStage.tilt_signs`)."""

    dofs: tuple[str, ...] = TILT_DEGREES_OF_FREEDOM
    gain: AdaptiveGain | ExponentialGain = field(default_factory=AdaptiveGain)
    camera_to_stage: CameraToStage = field(default_factory=CameraToStage)
    previous_velocity: np.ndarray | None = None
    previous_gain: float | None = None

    def reset(self) -> None:
        self.previous_velocity = self.previous_gain = None

    def step(self, alpha_deg: float, beta_deg: float, sampling_time_s: float, *,
             spread_deg: dict[str, float] | None = None) -> LawStep:
        """Error (rad), cost, gain, velocity (rad/s) and the stage's tilt move (degrees,
        ``move`` has "tilt_x_deg", "tilt_y_deg" for the chosen DOFs). ``spread_deg`` is
        not used (the paper's law takes the error as it is)."""
        error, interaction = tilt_error(alpha_deg, beta_deg, self.dofs)
        # The sweeps come at uneven intervals (one scanned during a tilt move is not
        # used, so the next interval is two sweeps long): eq. 37's previous velocity is
        # scaled to this interval's capped gain (a 5-DOF run moved beta 1.4 degrees on a
        # 0.44 degree error and overshot when it was not).
        gain, velocity, moved = velocity_and_displacement(error, interaction, self.gain(np.degrees(error)),
                                                          sampling_time_s, self.previous_velocity, self.previous_gain)
        self.previous_velocity, self.previous_gain = velocity, gain
        move = self.camera_to_stage.stage_move(dict(zip(self.dofs, moved)))
        return LawStep(_floats(error), cost(error), gain, _floats(velocity), move)


@dataclass
class PositionTiltLaw:
    """The tilts' position-based step (not in the paper; the tilts' part of
    ``law="position"``): the tilt error the focus sweeps since the last tilt move
    measured, undone in one move.

    Why: the paper's law (eq. 36-37, :class:`TiltLaw`), capped to approach without
    overshoot at the sweeps' sampling time, moves at most a third of the error per
    sweep, and every sweep is seconds of scanning: a 5-DOF run from 7 degrees took
    eight to ten tilt moves and hit its iteration limit on a real scene. The tilt stage
    is motorised and repeatable (no piezo hysteresis to model), so the measured error is
    commanded whole (``fraction``); what is left is the estimate's own error, which the
    next sweeps measure. The error is the theta-u vector of eq. 30 as for
    :class:`TiltLaw`; the move is its opposite, through the camera-to-stage tilt signs.

    Near the goal a whole step would turn the sweeps' noise into tilt (a reading of
    0.24 degree on a true 0.04, moved whole, leaves -0.20): given the measurement's
    standard error sigma, each DOF's step is shrunk by max(0, 1 - (sigma / e)^2), the
    positive-part James-Stein estimate of the true error (1 far away; 0.75 at e = 2
    sigma). The caller holds errors its sweeps cannot tell from zero and saturates at
    ``max_turn_deg``, as for the paper's law.
    """

    dofs: tuple[str, ...] = TILT_DEGREES_OF_FREEDOM
    camera_to_stage: CameraToStage = field(default_factory=CameraToStage)
    fraction: float = 1.0

    def reset(self) -> None:
        """Nothing carried from one step to the next."""

    def step(self, alpha_deg: float, beta_deg: float, sampling_time_s: float | None = None, *,
             spread_deg: dict[str, float] | None = None) -> LawStep:
        """Error (rad), cost, the mean fraction commanded (as the gain) and the stage's
        tilt move (degrees, "tilt_x_deg", "tilt_y_deg" for the chosen DOFs); no velocity.
        ``spread_deg``: the measured tilts' standard errors by DOF (degrees), if known."""
        error, _ = tilt_error(alpha_deg, beta_deg, self.dofs)
        fractions = np.full(len(self.dofs), float(self.fraction))
        for index, dof in enumerate(self.dofs):
            sigma, size = (spread_deg or {}).get(dof, 0.0), math.degrees(abs(float(error[index])))
            if sigma > 0:
                fractions[index] *= max(0.0, 1.0 - (sigma / size) ** 2) if size > 0 else 0.0
        move = self.camera_to_stage.stage_move(dict(zip(self.dofs, -fractions * error)))
        return LawStep(_floats(error), cost(error), float(fractions.mean()), (), move)


def make_tilt_law(name: str, dofs: Sequence[str], *, camera_to_stage: CameraToStage | None = None,
                  gain: AdaptiveGain | ExponentialGain | None = None) -> TiltLaw | PositionTiltLaw:
    """The tilt law that goes with the planar law ``name`` (one of :data:`LAWS`): the
    paper's (eq. 36-37) with ``law="paper"``, one whole step per measurement with
    ``law="position"``."""
    camera_to_stage = camera_to_stage or CameraToStage()
    if name == "paper":
        return TiltLaw(tuple(dofs), gain or AdaptiveGain(), camera_to_stage)
    if name == "position":
        return PositionTiltLaw(tuple(dofs), camera_to_stage)
    raise ValueError(f"unknown law {name!r}; laws: {', '.join(LAWS)}")


# --------------------------------------------------------------------------------------
# A position-based law (not in the paper): the measured displacement in one move

#: The laws a run may pick by name (the run settings' ``law``): the paper's (eq. 30-37)
#: and :class:`PositionLaw`.
LAWS = ("paper", "position")


def settling_time_s(step: float, time_constant_s: float, within: float) -> float:
    """How long a first-order axis takes to come within ``within`` of a step of ``step``
    (same units): tau ln(|step| / within), zero for a step already within."""
    if time_constant_s < 0 or within <= 0:
        raise ValueError("the time constant must not be negative and the band must be positive")
    return time_constant_s * math.log(abs(step) / within) if abs(step) > within else 0.0


@dataclass(frozen=True)
class StageSettling:
    """A stage's settling, per axis of a move ("x_um", "rotation_deg", ...): a first-order
    response with time constant ``time_constants_s[axis]``, settled when within
    ``within[axis]`` of the target. What a stage service reports as ``settled_at_ns`` on a
    move's reply (the write time plus :meth:`after_s` of the move), and what the in-process
    loop (:mod:`semservo.reproduce.loop`) waits for. The defaults: a small piezo stage
    (settling "around 10 ms", ``shared/reference/nv403-and-tritor.md``: tau 3 ms, within
    1 nm: 10 ms for 30 nm, 28 ms for 10 um)."""

    time_constants_s: dict = field(default_factory=lambda: {"x_um": 0.003, "y_um": 0.003})
    within: dict = field(default_factory=lambda: {"x_um": 0.001, "y_um": 0.001})

    def after_s(self, move: dict[str, float]) -> float:
        """Seconds from the write until every axis of ``move`` has settled (the slowest)."""
        times = [settling_time_s(value, self.time_constants_s[axis], self.within[axis])
                 for axis, value in move.items() if axis in self.time_constants_s]
        return max(times, default=0.0)


#: A move's response is judged (:class:`UnexpectedResponse`) only when the content
#: should have moved more than this (px for x/y, degrees for the rotation) and five times
#: the estimate's noise: the corrections near the target are a few tenths of a pixel,
#: where a frame's vibration and noise (0.1-0.4 px at x3000-x5000, more than the noise
#: learned between moves) made a right stage look wrong twice (a 5-DOF run read -0.46 x).
#: A wrong sign or a blocked axis shows on the large first moves, and the divergence
#: check holds for the rest.
RESPONSE_JUDGED_ABOVE = {"x/y": 1.0, "rotation": 0.2}


class UnexpectedResponse(RuntimeError):
    """The stage did not move the content as commanded, twice in a row on one axis (a
    wrong sign of the camera-to-stage transform, a blocked axis, a wrong estimate): the
    run must stop rather than move again."""


#: The position law's prior spread of the stage's gain, by what the stage service maps
#: micrometres to volts with.
MODEL_UNCERTAINTY = {"calibrated": 0.15, "uncalibrated": 0.7}

#: Which stage axis (a key of a move) carries which degree of freedom, and its units.
_AXIS_OF = {"x": "x_um", "y": "y_um", "rotation": "rotation_deg"}


@dataclass
class PositionLaw:
    """A position-based law (not the paper's): each fresh frame measures the whole
    remaining displacement, so one move commands all of it through the stage's
    displacement model (the stage service maps micrometres to volts), shortened only as
    far as the stage's response is uncertain; the next fresh frame measures what is left,
    and with it how the stage responded, and the law corrects the residue with what it
    learned. From a calibrated model a target is reached in two to four moves; an
    uncalibrated stage (70 % uncertain) takes a cautious first move, learns its gain from
    it and closes in from the same side.

    The state estimator is a linear Kalman filter, per degree of freedom: the content's
    position error p (px, or degrees for the rotation), its drift v (per second) and the
    stage axis's gain k (the move it makes over the move it is told; prior 1 with the
    displacement model's relative uncertainty). A frame measures p (noise: the estimate's
    per frame, below); time adds v dt; a move u adds M diag(u) k (M: the camera-to-stage transform's
    content motion per unit move), linear in the state, so p, v and k are estimated
    together. A reversal of an axis's direction starts a minor hysteresis loop of another
    gain: k's spread is raised to ``reversal_spread`` there. The last move's planar part
    creeps on (``creep_per_decade`` of it per decade of time after its write, until the
    next move; a chained move counts as written with its last command): time adds that
    too, through k, so creep is neither read as drift nor as the stage's gain. A tilt that
    moves the view (:meth:`view_moved`) restarts the position only; the drift learned
    stays.

    The estimate's noise is not always white: a vibration faster than a frame leaves each
    frame's estimate off by what the scan's texture weighting makes of it, and at x5000
    (7 Hz, 2.54 cycles a frame) consecutive frames are off by nearly opposite amounts
    (lag-1 correlation -0.5 to -0.9 over ten simulated scenes; the mean of two frames 0.01-
    0.02 px from the truth where one frame is 0.03-0.12). So the noise is a state too, e
    per DOF (a frame measures p + e), an AR(1) process over frames: e' = phi^g e over a gap
    of g frames, stationary variance sigma^2 (:meth:`noise_model`); over a gap that is
    not a whole number of frames (an image source resting between scans for varying
    times) the phase is lost and e starts afresh. sigma and phi are learned from the
    frames at rest (no move between them), by the variogram: half the mean squared
    difference of frames 1 and 2 apart, D1 = sigma^2 (1 - phi) and D2 = sigma^2 (1 -
    phi^2). D1 is pooled with a white prior (``noise_px``, ``noise_weight`` pairs); phi =
    D2 / D1 - 1 is measured on triples of consecutive frames only (so both lags have as
    many pairs; a noise above the prior then does not read as a correlation), shrunk
    towards 0 by the prior's weight, and only a negative phi (down to
    ``noise_correlation_floor``) is used: a positive one, in a few frames, is
    indistinguishable from the drift and the creep the state already has. With phi = 0
    the filter's equations are the white-noise filter's.

    Each fresh frame: converged (:attr:`converged`) when the error predicted for now,
    plus one standard deviation, is within tolerance, and so is the error the last move's
    creep leads to within ``creep_horizon_s``, and no move is due (below); else a move
    when the error predicted
    for the next fresh frame is beyond ``deadband`` x tolerance and ``significance``
    standard deviations (or the creep ahead carries it beyond tolerance): u = -(M diag(k +
    ``caution`` spread(k)))^-1 p / (1 + the move's own creep to midway, in decades, between
    the next frame and the horizon), so a gain up to ``caution`` spreads above the estimate
    does not overshoot; else held for another frame.

    Safety: every move within ``max_move_um`` (planar, the direction kept) and
    ``max_turn_deg``; once a move of this run has moved the content as commanded (a
    response judged plausible, below), a planar move may reach ``max_moves`` x
    ``max_move_um``, which the caller makes as the fewest equal commands of at most
    ``max_move_um`` (:func:`move_pieces`), each written after the last has settled: a 30 %
    offset is then one frame's work, not three, while a first move, on a stage not yet
    seen to respond, stays within one ``max_move_um``; noise is not chased; a response
    implausible (the content moved less
    than 0.2 or more than 5 times the commanded move, or the wrong way) on the first fresh
    frame after a move is asked again on the next one without moving (a move that landed
    late reads as none); implausible there too, it counts, and two such moves in a row on
    one axis group raise :class:`UnexpectedResponse`.

    What the caller (the controller) provides, each iteration:

    * only frames it would act on: the estimate's confidence at least the run's
      ``min_confidence`` (else pass ``confident=False``, or do not call; either way
      nothing moves and nothing is learned);
    * ``fresh``: whether the frame was scanned wholly after the last move had settled,
      i.e. its scan started at or after the ``settled_at_ns`` of the stage's reply to the
      last move (:class:`StageSettling`). A frame that is not fresh shows a pose in
      between: the law neither moves nor learns on it;
    * the estimate (dx, dy px; rotation degrees) and the frame's pixel size (nm);
      ``sampling_time_s`` is accepted (the paper's law needs it) and unused;
    * with ``partial_frames``, a frame may be the rows of a scan that were scanned after the
      last move had settled (at least :data:`~semservo.estimation.raster.PARTIAL_FRAME_FROM` of them): then
      ``frame_interval_s`` spans those rows and ``scan_time_s`` is the whole scan's time;
    * ``frame_interval_s``: when the frame's scan started and ended, and ``now_s``: when
      the move will be written (default: the frame's end), in seconds on one clock (the
      image source's when it has one; the same clock for :meth:`applied`). Without them
      the law assumes no drift;
    * after writing the move: :meth:`applied` with the move as the stage carried it out
      (after any saturation of the caller's own) and ``at_s``, when it was written, or
      with None / {} when the stage refused it or nothing was written. A move not
      confirmed is taken as not made;
    * the run converges when :attr:`converged` is True after a step (instead of the
      controller's mean of the last N frames, some of which measured a pose left behind);
      with ``hold`` the caller keeps calling: the law corrects only what drifts beyond the
      dead band.

    The result is a :class:`LawStep`: ``error`` (px, rad) of this frame, ``cost``, ``gain``
    the fraction of the predicted error the move commands (1: all of it; 0: held),
    ``velocity`` empty (a displacement is commanded, not a velocity), ``move`` by stage axis.
    """

    dofs: tuple[str, ...] = ("x", "y")
    camera_to_stage: CameraToStage = field(default_factory=CameraToStage)
    #: The stage's displacement model, relative 1-sigma of k: 0.15 calibrated (the model's
    #: branches are the major loop; a servo's small moves run on minor loops whose gain is
    #: 70-100 % of it), 0.7 none (a linear model from the nominal stroke: a piezo moves
    #: 1-1.7 x what 100 um over 150 V says, depending on where and which way).
    #: :data:`MODEL_UNCERTAINTY` has both.
    model_uncertainty: float = 0.15
    reversal_spread: float = 0.2
    tolerance_px: float = 0.1
    tolerance_deg: float = 0.05
    deadband: float = 0.7
    max_move_um: float = 10.0
    #: Moves of at most ``max_move_um`` a planar step may take once the stage has responded
    #: as commanded in this run (1: one per frame).
    max_moves: int = 1
    max_turn_deg: float = 5.0
    caution: float = 1.0
    significance: float = 2.0
    noise_px: float = 0.03  # the estimate's noise per frame at rest (prior), px
    noise_deg: float = 0.01  # and for the rotation, degrees
    noise_weight: float = 3.0  # the prior's weight, in frame pairs (it also shrinks the learned correlation)
    #: The most negative lag-1 correlation of the estimate's noise the law believes (the
    #: variogram's estimate is clipped to [this, 0]).
    noise_correlation_floor: float = -0.9
    #: Thermal drift of the sample: the prior's spread and how fast it may change (nm/s,
    #: nm/s per sqrt s; "nanometres per second to per minute").
    drift_nm_per_s: float = 3.0
    drift_walk_nm: float = 0.1
    #: The fraction of a move's size the gain k does not explain (hysteresis minor loops,
    #: creep).
    unmodelled: float = 0.05
    #: How much k may change per micrometre (or degree) of travel, relative to the model's
    #: uncertainty: a piezo's gain varies along its stroke (a linear model's far more than
    #: a calibrated model's), so what the last moves taught fades with the travel.
    gain_walk: float = 0.05
    #: Creep (``shared/reference/nv403-and-tritor.md``: "about 1-2 % of the last move per
    #: decade of time after a step"): after a move written at t_w, the content goes on by
    #: ``creep_per_decade`` x the move's content motion x log10(1 + (t - t_w) /
    #: ``creep_start_s``), until the next move; ``creep_spread`` its relative 1-sigma. 0 for
    #: a closed-loop stage (a driver in physical units).
    creep_per_decade: float = 0.015
    creep_start_s: float = 0.1
    creep_spread: float = 0.5
    #: Arrival is declared only if the last move's creep over this many seconds keeps the
    #: target within tolerance (else the residue is trimmed first: a 50 px move creeps
    #: 0.75 px per decade, so arrival on the frame after it would not hold).
    creep_horizon_s: float = 10.0
    #: Converged when the error now plus this many of its standard deviations is within
    #: tolerance.
    margin: float = 1.0
    #: The caller acts on a scan's rows scanned after a move settled (a partial frame,
    #: above), so the next frame measured after a move is the rest of the scan the move
    #: lands in, not the scan after it: the law aims for that frame's time.
    partial_frames: bool = False
    #: True after a step that put the target within tolerance.
    converged: bool = False
    state: np.ndarray | None = field(default=None, repr=False)  # [p, v, k, e] per DOF
    covariance: np.ndarray | None = field(default=None, repr=False)
    _time: float | None = field(default=None, repr=False)  # the state's time
    _pixel_size_nm: float | None = field(default=None, repr=False)
    _pending: dict | None = field(default=None, repr=False)  # last move applied, not yet seen
    #: The last two frames at rest since the last move: (the frame's middle, s, or None
    #: without a clock; its planar error); and the variogram of the frames at rest: the
    #: sum of half squared differences of consecutive frames and their pairs, and over
    #: triples of consecutive frames, the sums at lag 1 and at lag 2 and the triples.
    _at_rest: list = field(default_factory=list, repr=False)
    _variogram: list = field(default_factory=lambda: [0.0, 0, 0.0, 0.0, 0], repr=False)
    _measured_middle: float | None = field(default=None, repr=False)  # the last frame measured's middle (s)
    _frame_middle: float | None = field(default=None, repr=False)  # the last frame's middle (s)
    _frame_period: float | None = field(default=None, repr=False)  # the stream's, as seen (s)
    _directions: dict = field(default_factory=dict, repr=False)
    _implausible: dict = field(default_factory=dict, repr=False)
    _kept_gains: tuple | None = field(default=None, repr=False)
    _kept_drift: tuple | None = field(default=None, repr=False)  # drift and its covariance across a view's move
    _responded: bool = field(default=False, repr=False)  # a planar move of this run judged plausible
    _creeping: tuple | None = field(default=None, repr=False)  # the last move: (u, written at s), creeping

    def __post_init__(self):
        unknown = set(self.dofs) - set(_AXIS_OF)
        if unknown:
            raise ValueError(f"the position law drives {', '.join(_AXIS_OF)}; not {sorted(unknown)}")
        self.axes = tuple(_AXIS_OF[dof] for dof in self.dofs)
        self._rotation = np.array([dof == "rotation" for dof in self.dofs])

    # -- the estimator ---------------------------------------------------------------
    def reset(self) -> None:
        """Forget the run: position and drift (the stage's gains and the noise learned stay)."""
        n = len(self.dofs)
        kept = None
        if self.state is not None:
            kept = self.state[2 * n:3 * n].copy(), self.covariance[2 * n:3 * n, 2 * n:3 * n].copy()
        self.state = self.covariance = None
        self._time = self._pending = self._creeping = self._measured_middle = None
        self._at_rest = []
        self._implausible, self.converged, self._responded = {}, False, False
        self._kept_gains, self._kept_drift = kept, None

    def view_moved(self) -> None:
        """The view moved by design (a tilt about a pivot below the surface shifts it): the
        position starts afresh from the next fresh frame; what was learned of the sample's
        drift, of the stage's gains and response, and of the noise stays. Without the
        restart, the view's jump would read as the stage's implausible response to the
        last planar move; the drift is the sample's (thermal), which a turn of the cradle
        does not change, so a run that tilts often (5-DOF) need not learn it again from
        its prior after every tilt move."""
        n = len(self.dofs)
        drift = self._kept_drift
        if self.state is not None:
            drift = self.state[n:2 * n].copy(), self.covariance[n:2 * n, n:2 * n].copy()
        gains, responded = self._kept_gains, self._responded
        self.reset()
        if self._kept_gains is None:  # no state yet: what an earlier run left stays
            self._kept_gains = gains
        self._kept_drift, self._responded = drift, responded

    def noise(self) -> np.ndarray:
        """The estimate's noise per frame (px, or degrees for the rotation), per DOF: sigma."""
        return self.noise_model()[0]

    def noise_model(self) -> tuple[np.ndarray, np.ndarray]:
        """The estimate's noise per DOF: sigma (px, degrees for the rotation) and phi, the
        lag-1 correlation of consecutive frames' noise (the class docstring's variogram;
        the rotation's noise is taken as white, from its prior)."""
        weight, prior = self.noise_weight, self.noise_px**2
        lag1_total, pairs, triple_lag1, triple_lag2, triples = self._variogram
        lag1 = (weight * prior + lag1_total) / (weight + pairs)
        correlation = 0.0
        if triples and triple_lag1 > 0:
            shrink = triples / (triples + weight)
            correlation = float(np.clip(shrink * (triple_lag2 / triple_lag1 - 1.0), self.noise_correlation_floor, 0.0))
        sigma = math.sqrt(lag1 / (1.0 - correlation))
        return (np.where(self._rotation, self.noise_deg, sigma),
                np.where(self._rotation, 0.0, correlation))

    def gains(self) -> dict[str, tuple[float, float]]:
        """The stage's gain k per axis, with its spread."""
        n = len(self.dofs)
        if self.state is None:
            return {axis: (1.0, self.model_uncertainty) for axis in self.axes}
        return {axis: (float(self.state[2 * n + i]), float(math.sqrt(self.covariance[2 * n + i, 2 * n + i])))
                for i, axis in enumerate(self.axes)}

    def _start(self, error: np.ndarray) -> None:
        n = len(self.dofs)
        self.state = np.concatenate([error, np.zeros(n), np.ones(n), np.zeros(n)])
        noise = self.noise()
        drift_px = self.drift_nm_per_s / self._pixel_size_nm
        self.covariance = np.diag(np.concatenate([noise**2, np.where(self._rotation, 0.0, drift_px**2),
                                                  np.full(n, self.model_uncertainty**2), noise**2]))
        # The frame measured p + e: the position is off by the frame's noise, e, exactly.
        self.covariance[:n, 3 * n:] = self.covariance[3 * n:, :n] = -np.diag(noise**2)
        if self._kept_gains is not None:  # learned in an earlier run on this stage
            self.state[2 * n:3 * n], self.covariance[2 * n:3 * n, 2 * n:3 * n] = self._kept_gains
        if self._kept_drift is not None:  # learned in this run before the view moved
            self.state[n:2 * n], self.covariance[n:2 * n, n:2 * n] = self._kept_drift

    def _content_per_move(self, pixel_size_nm: float) -> np.ndarray:
        """M: the content's motion (px, degrees) per unit move of each stage axis."""
        n = len(self.dofs)
        matrix = np.zeros((n, n))
        for column, axis in enumerate(self.axes):
            if axis == "rotation_deg":
                matrix[column, column] = self.camera_to_stage.rotation_sign
                continue
            content = self.camera_to_stage.content_move_px(1.0 if axis == "x_um" else 0.0,
                                                          1.0 if axis == "y_um" else 0.0, pixel_size_nm)
            for row, dof in enumerate(self.dofs):
                if dof in ("x", "y"):
                    matrix[row, column] = content[0 if dof == "x" else 1]
        return matrix

    def _creep_fraction(self, elapsed_s: float) -> float:
        """The fraction of a move it has crept ``elapsed_s`` after its write."""
        return self.creep_per_decade * math.log10(1.0 + max(elapsed_s, 0.0) / self.creep_start_s)

    def _creep_per_gain(self, from_s: float | None, to_s: float | None) -> np.ndarray:
        """The content's creep between two times per unit of the stage's gains k (n x n:
        the creep is this times k), from the last move; zeros without one."""
        n = len(self.dofs)
        if from_s is None or to_s is None or self._creeping is None or to_s <= from_s:
            return np.zeros((n, n))
        move, written = self._creeping
        fraction = self._creep_fraction(to_s - written) - self._creep_fraction(from_s - written)
        return fraction * self._content_per_move(self._pixel_size_nm) @ np.diag(move)

    def _creep(self, from_s: float | None, to_s: float | None) -> tuple[np.ndarray, np.ndarray]:
        """The content's creep (per DOF, px) between two times, through the gains as
        estimated, and its spread."""
        n = len(self.dofs)
        creep = self._creep_per_gain(from_s, to_s) @ self.state[2 * n:3 * n]
        return creep, self.creep_spread * np.abs(creep)

    def _predict(self, to_s: float | None) -> None:
        if to_s is None:  # no clock: no drift
            return
        if self._time is None or to_s <= self._time:
            self._time = to_s if self._time is None else self._time
            return
        n = len(self.dofs)
        dt = to_s - self._time
        transition = np.eye(4 * n)
        transition[:n, n:2 * n] = np.eye(n) * dt
        _, creep_spread = self._creep(self._time, to_s)
        transition[:n, 2 * n:3 * n] = self._creep_per_gain(self._time, to_s)  # the last move's creep: linear in k
        self.state = transition @ self.state
        self.covariance = transition @ self.covariance @ transition.T
        walk = np.where(self._rotation, 0.0, (self.drift_walk_nm / self._pixel_size_nm) ** 2 * dt)
        self.covariance[n:2 * n, n:2 * n] += np.diag(walk)
        self.covariance[:n, :n] += np.diag(creep_spread**2)
        self._time = to_s

    def _apply_move(self, move: dict[str, float]) -> None:
        n = len(self.dofs)
        commanded = np.array([move.get(axis, 0.0) for axis in self.axes])
        for index, axis in enumerate(self.axes):
            direction = int(np.sign(commanded[index]))
            if direction and self._directions.get(axis, direction) != direction:
                gain_index = 2 * n + index
                self.covariance[gain_index, gain_index] = max(self.covariance[gain_index, gain_index],
                                                              self.reversal_spread**2)
            if direction:
                self._directions[axis] = direction
        walk = (self.gain_walk * self.model_uncertainty * np.abs(commanded)) ** 2
        self.covariance[2 * n:3 * n, 2 * n:3 * n] += np.diag(walk)
        per_move = self._content_per_move(self._pixel_size_nm)
        transition = np.eye(4 * n)
        transition[:n, 2 * n:3 * n] = per_move @ np.diag(commanded)
        self.state = transition @ self.state
        self.covariance = transition @ self.covariance @ transition.T
        content = np.abs(per_move @ commanded)
        self.covariance[:n, :n] += np.diag((self.unmodelled * content) ** 2)
        # The last move's planar part creeps from its write on (a piezo's; the rotation
        # stage's gears do not); the move before stops creeping.
        planar = np.where(self._rotation, 0.0, commanded)
        self._creeping = ((planar, self._time) if self._time is not None and self.creep_per_decade > 0 and planar.any()
                          else None)

    def _advance_noise(self, frames: int | None) -> None:
        """The noise state e over ``frames`` frames: e' = phi^frames e, its variance
        topped up to the stationary sigma^2 (None: not a whole number of frames, e afresh;
        0: the same frame again, the same e)."""
        n = len(self.dofs)
        sigma, correlation = self.noise_model()
        carried = np.zeros_like(correlation) if frames is None else correlation ** frames
        transition = np.eye(4 * n)
        transition[3 * n:, 3 * n:] = np.diag(carried)
        self.state = transition @ self.state
        self.covariance = transition @ self.covariance @ transition.T
        self.covariance[3 * n:, 3 * n:] += np.diag(sigma**2 * (1.0 - carried**2))

    def _measure(self, error: np.ndarray) -> None:
        """A frame measures p + e (and a white floor of a thousandth of sigma, for the
        filter's numerics)."""
        n = len(self.dofs)
        observation = np.zeros((n, 4 * n))
        observation[:, :n] = observation[:, 3 * n:] = np.eye(n)
        innovation = error - observation @ self.state
        innovation_covariance = (observation @ self.covariance @ observation.T
                                 + np.diag((1e-3 * self.noise()) ** 2))
        gain = self.covariance @ observation.T @ np.linalg.inv(innovation_covariance)
        self.state = self.state + gain @ innovation
        self.covariance = (np.eye(4 * n) - gain @ observation) @ self.covariance
        self.covariance = (self.covariance + self.covariance.T) / 2

    def _see_frame(self, middle: float | None, frame_time: float) -> None:
        """The stream's frame period: the scan's time (a continuously scanning SEM's
        period; a source that rests between scans makes the gaps fractional, and the
        noise's phase is then not followed), or, for frames whose interval has no length
        (an acquisition time only), the shortest interval seen between two frames."""
        if middle is None:
            return
        if frame_time > 0:
            self._frame_period = frame_time
        elif self._frame_middle is not None and middle > self._frame_middle:
            self._frame_period = min(self._frame_period or math.inf, middle - self._frame_middle)
        self._frame_middle = middle

    def _frames_between(self, earlier: float | None, later: float | None) -> int | None:
        """Whole frames from one frame's middle to another's: 1 without a clock, None
        when the gap is not within a quarter frame of a whole number (or no period is
        known yet)."""
        if earlier is None or later is None:
            return 1
        if not self._frame_period:
            return None
        frames = (later - earlier) / self._frame_period
        whole = int(round(frames))
        return whole if whole >= 0 and abs(frames - whole) <= 0.25 else None

    def _learn_noise(self, middle: float | None, error: np.ndarray) -> None:
        """The variogram of the frames at rest since the last move, over triples of
        consecutive frames (lags 1 and 2 together). Planar DOFs only (the rotation's
        noise is its prior): a rotation-only law learns nothing here."""
        planar = error[~self._rotation]
        if not planar.size:
            return
        if not self._at_rest:
            self._at_rest = [(middle, planar)]
            return
        last_middle, last = self._at_rest[-1]
        lag1 = float(((planar - last) ** 2).mean()) / 2
        if self._frames_between(last_middle, middle) == 1:
            self._variogram[0] += lag1
            self._variogram[1] += 1
            if len(self._at_rest) == 2 and self._frames_between(*(entry[0] for entry in self._at_rest)) == 1:
                self._variogram[2] += lag1
                self._variogram[3] += float(((planar - self._at_rest[0][1]) ** 2).mean()) / 2
                self._variogram[4] += 1
        self._at_rest = (self._at_rest + [(middle, planar)])[-2:]

    def _check_response(self, error: np.ndarray) -> bool:
        """The move just seen: the content's motion against the motion the move should
        have made, for the planar axes together and for the rotation. False: implausible
        on this first frame after the move, so the frame is not used and the next one is
        asked again (a move that landed late, after the frame's scan began, reads as no
        move at all; a loaded computer's emulated amplifier did that); implausible on
        that second frame too, it counts."""
        n = len(self.dofs)
        before, move = self._pending["before"], self._pending["move"]
        commanded = np.array([move.get(axis, 0.0) for axis in self.axes])
        expected = self._content_per_move(self._pixel_size_nm) @ commanded
        achieved = error - before
        for group, chosen in (("x/y", ~self._rotation), ("rotation", self._rotation)):
            if not chosen.any():
                continue
            size = float(np.hypot.reduce(expected[chosen]))
            if size <= max(5 * float(self.noise()[chosen].max()), RESPONSE_JUDGED_ABOVE[group]):
                continue
            ratio = float(achieved[chosen] @ expected[chosen]) / size**2
            if 0.2 <= ratio <= 5.0:
                self._implausible[group] = 0
                self._responded = self._responded or group == "x/y"
                continue
            if not self._pending.get("asked_again"):
                self._pending["asked_again"] = True
                return False
            self._implausible[group] = self._implausible.get(group, 0) + 1
            # Learn nothing from it: the gains are held where they were.
            for index in np.flatnonzero(chosen):
                self.covariance[2 * n + index, :] = 0.0
                self.covariance[:, 2 * n + index] = 0.0
                self.covariance[2 * n + index, 2 * n + index] = self._pending["gain_variance"][index]
            if self._implausible[group] >= 2:
                raise UnexpectedResponse(
                    f"{group}: the stage moved the content {ratio:+.2f} x the commanded move twice in a row "
                    "(a wrong camera-to-stage sign, a blocked axis, or wrong estimates)")
        return True

    # -- the law ---------------------------------------------------------------------
    def applied(self, move: dict[str, float] | None, at_s: float | None = None) -> None:
        """The move the stage carried out after the last step (None or {}: none), written
        at ``at_s`` (on the clock of ``frame_interval_s``)."""
        if not move or self.state is None:
            return
        move = {axis: value for axis, value in move.items() if axis in self.axes}
        n = len(self.dofs)
        self._predict(at_s)
        self._pending = {"before": self.state[:n].copy(), "move": dict(move),
                         "gain_variance": np.diag(self.covariance)[2 * n:3 * n].copy()}
        self._apply_move(move)
        if at_s is None:  # no clock: the creep cannot be followed
            self._creeping = None
        self._at_rest = []

    def step(self, dx_px: float, dy_px: float, rotation_deg: float, pixel_size_nm: float,
             sampling_time_s: float | None = None, *, fresh: bool = True, confident: bool = True,
             frame_interval_s: tuple[float, float] | None = None, now_s: float | None = None,
             scan_time_s: float | None = None) -> LawStep:
        """One frame in, the move out (see the class for what the caller provides)."""
        if not fresh or not confident:
            return LawStep.idle()
        error = error_vector(dx_px, dy_px, rotation_deg, self.dofs)
        units = error_in_units(error, self.dofs)
        n = len(self.dofs)
        if self._pixel_size_nm is not None and abs(pixel_size_nm - self._pixel_size_nm) > 1e-9 * pixel_size_nm:
            self.reset()  # another magnification: the position in pixels starts afresh
        self._pixel_size_nm = pixel_size_nm
        middle = None if frame_interval_s is None else (frame_interval_s[0] + frame_interval_s[1]) / 2
        now = now_s if now_s is not None else (frame_interval_s[1] if frame_interval_s else None)
        frame_time = (frame_interval_s[1] - frame_interval_s[0]) if frame_interval_s else 0.0
        if scan_time_s:  # the rows of a scan after a move settled: the scan's own time is the period
            frame_time = scan_time_s
        self._see_frame(middle, frame_time)
        if self.state is None:
            self._start(units)
            self._time = middle
        else:
            self._predict(middle)
            if self._pending is not None:
                if not self._check_response(units):
                    return LawStep(_floats(error), cost(error), 0.0, (), {},
                                   held="held: the last move not seen yet (asked again on the next frame)")
            else:  # the same pose as the frames before: their differences are the noise's
                self._learn_noise(middle, units)
            self._advance_noise(self._frames_between(self._measured_middle, middle))
            self._measure(units)
        if self._pending is not None or not self._at_rest:  # the first frame at this pose
            self._at_rest = [(middle, units[~self._rotation])]
        self._pending, self._measured_middle = None, middle
        # Where the target is now, and at the middle of the next fresh frame: the rest of
        # the scan the move lands in (partial frames, when enough of it is left), else the
        # scan after it (one and a half frames on).
        next_frame = None if now is None else now + 1.5 * frame_time
        if self.partial_frames and now is not None and frame_interval_s is not None and frame_time > 0:
            landing_scan_ends = frame_interval_s[1] + frame_time
            if landing_scan_ends - now >= PARTIAL_FRAME_FROM * frame_time:
                next_frame = (now + landing_scan_ends) / 2
        position, spread = self._forecast(now)
        aim, aim_spread = self._forecast(next_frame)
        # Where the last move's creep takes the content if nothing moves (a move stops it).
        creep_ahead, creep_ahead_spread = self._creep(now, None if now is None else now + self.creep_horizon_s)
        ahead = position + creep_ahead
        ahead_spread = np.hypot(spread, creep_ahead_spread)
        tolerances = np.where(self._rotation, self.tolerance_deg, self.tolerance_px)
        planar, rotation = self._norms(position), self._norms(position, rotation=True)
        planar_spread = self._norms(spread) / math.sqrt(max(sum(~self._rotation), 1))
        planar_ahead = self._norms(ahead)
        planar_ahead_spread = self._norms(ahead_spread) / math.sqrt(max(sum(~self._rotation), 1))
        # Act on what is significant now; aim at where the drift will have taken it (a
        # converged run that holds still corrects what will have drifted beyond the dead band).
        act = (np.abs(aim) > self.deadband * tolerances) & (np.abs(position) > self.significance * spread)
        # The planar DOFs act together (a diagonal error is one error); a creep that will
        # carry the content beyond tolerance is trimmed now.
        if (~self._rotation).any():
            act[~self._rotation] = ((self._norms(aim) > self.deadband * self.tolerance_px
                                     and planar > self.significance * planar_spread)
                                    or (planar_ahead > self.tolerance_px
                                        and planar_ahead > self.significance * planar_ahead_spread))
        # Arrived: within tolerance by a margin, now and as far as the last move's creep
        # goes within the horizon, and nothing left the law would still trim (a residue
        # beyond the dead band that the frames show clearly: stopping there leaves the
        # stage at the tolerance's edge, where a bias of the estimate or the next creep
        # puts it beyond).
        self.converged = bool(planar + self.margin * planar_spread <= self.tolerance_px
                              and planar_ahead + self.margin * planar_ahead_spread <= self.tolerance_px
                              and rotation + self.margin * self._norms(spread, rotation=True) <= self.tolerance_deg
                              and not act.any())
        if not act.any():
            return LawStep(_floats(error), cost(error), 0.0, (), {})
        gains = self.state[2 * n:3 * n]
        spreads = np.sqrt(np.diag(self.covariance)[2 * n:3 * n])
        # Reversals raise the spread before the move: the first move of a minor loop is cautious.
        per_move = self._content_per_move(pixel_size_nm)
        # A move stops the last one's creep: aim at where the content is when it is written,
        # plus the drift until the next frame; and the move's own creep carries it on, so
        # it is shortened to put the target midway (in decades) between the next frame and
        # the horizon.
        aim = aim - self._creep(now, next_frame)[0]
        own_creep = 0.0
        if next_frame is not None:
            lag = next_frame - now
            own_creep = (self._creep_fraction(lag) + self._creep_fraction(lag + self.creep_horizon_s)) / 2
        nominal = np.linalg.solve(per_move, -np.where(act, aim, 0.0))  # the move at k = 1
        nominal = np.where(self._rotation, nominal, nominal / (1.0 + own_creep))
        for index, axis in enumerate(self.axes):
            direction = int(np.sign(nominal[index]))
            if direction and self._directions.get(axis, direction) != direction:
                spreads[index] = max(spreads[index], self.reversal_spread)
        # The gain may wander over the travel of this move too.
        spreads = np.hypot(spreads, self.gain_walk * self.model_uncertainty * np.abs(nominal / np.maximum(gains, 0.2)))
        commanded = nominal / np.maximum(gains + self.caution * spreads, 0.2)
        move = {axis: float(value) for axis, value, acting in zip(self.axes, commanded, act) if acting}
        planar_move = math.hypot(move.get("x_um", 0.0), move.get("y_um", 0.0))
        limit = self.max_move_um * (max(int(self.max_moves), 1) if self._responded else 1)
        if planar_move > limit:
            # Saturated: even the cautious move is beyond the limit, so the target lies
            # beyond the limit's move too; go the limit's length towards it.
            direction = {axis: float(value) for axis, value in zip(self.axes, nominal / np.maximum(gains, 0.2))
                         if axis in ("x_um", "y_um") and axis in move}
            length = math.hypot(*direction.values())
            for axis, value in direction.items():
                move[axis] = value * limit / length
        if "rotation_deg" in move and abs(move["rotation_deg"]) > self.max_turn_deg:
            move["rotation_deg"] = math.copysign(self.max_turn_deg, move["rotation_deg"])
        fraction = float(np.mean([move[axis] / nominal[i] for i, axis in enumerate(self.axes)
                                  if axis in move and nominal[i]]))
        return LawStep(_floats(error), cost(error), fraction, (), move)

    def planar_estimate(self) -> tuple[float, float]:
        """The planar error as the law estimates it (px: over the planar DOFs it servoes)
        and its spread (one standard deviation, px), at the last frame; (nan, nan) before
        the first, and for a law that servoes no planar DOF (it estimates none)."""
        if self.state is None or self._rotation.all():
            return math.nan, math.nan
        position, spread = self._forecast(None)
        return self._norms(position), self._norms(spread) / math.sqrt(max(sum(~self._rotation), 1))

    def turn_estimate(self) -> tuple[float, float]:
        """The turn about the beam as the law estimates it (|degrees|) and its spread (one
        standard deviation), at the last frame: what its convergence judges the turn on;
        (nan, nan) before the first frame, and for a law that servoes no turn."""
        if self.state is None or not self._rotation.any():
            return math.nan, math.nan
        position, spread = self._forecast(None)
        return self._norms(position, rotation=True), self._norms(spread, rotation=True)

    def _forecast(self, at_s: float | None) -> tuple[np.ndarray, np.ndarray]:
        """The error predicted at ``at_s`` (drift and the last move's creep) and its
        spread, per DOF."""
        n = len(self.dofs)
        dt = 0.0 if at_s is None or self._time is None else max(at_s - self._time, 0.0)
        creep, creep_spread = self._creep(self._time, at_s)
        position = self.state[:n] + self.state[n:2 * n] * dt + creep
        variance = (np.diag(self.covariance)[:n] + 2 * dt * np.diag(self.covariance[:n, n:2 * n])
                    + dt**2 * np.diag(self.covariance)[n:2 * n] + creep_spread**2)
        return position, np.sqrt(np.maximum(variance, 0.0))

    def _norms(self, values: np.ndarray, rotation: bool = False) -> float:
        """The planar norm (px) of per-DOF values, or with ``rotation`` the rotation's |value|."""
        chosen = values[self._rotation] if rotation else values[~self._rotation]
        return float(np.hypot(*chosen)) if chosen.size == 2 else float(np.abs(chosen).sum())


def planar_limit_um(law: ControlLaw | PositionLaw, max_move_um: float, moves_per_frame: int) -> float:
    """The largest planar move one frame's step may make: the position law may chain
    ``moves_per_frame`` commands of ``max_move_um`` (it asks for more than one only once
    the stage has responded as commanded); the paper's law makes one."""
    return max_move_um * (moves_per_frame if isinstance(law, PositionLaw) else 1)


def saturate_planar(move: dict[str, float], limit_um: float) -> tuple[dict[str, float], bool]:
    """``move`` with its planar part (``x_um``, ``y_um``) scaled down to ``limit_um``, its
    direction kept, and whether it had to be."""
    planar = math.hypot(move.get("x_um", 0.0), move.get("y_um", 0.0))
    if planar <= limit_um:
        return dict(move), False
    return {axis: value * limit_um / planar if axis in ("x_um", "y_um") else value
            for axis, value in move.items()}, True


def move_pieces(move: dict[str, float], max_move_um: float) -> list[dict[str, float]]:
    """A move as the stage makes it: the planar part (``x_um``, ``y_um``) in the fewest
    equal pieces of at most ``max_move_um`` each (the direction kept), any other axis
    (a turn) with the first piece. A move within the limit is one piece; the caller
    writes each piece after the one before has settled and within the stage's rate."""
    planar = math.hypot(move.get("x_um", 0.0), move.get("y_um", 0.0))
    count = max(math.ceil(planar / max_move_um - 1e-9), 1) if planar > 0 else 1
    pieces = [{axis: value / count for axis, value in move.items() if axis in ("x_um", "y_um")}
              for _ in range(count)]
    pieces[0].update({axis: value for axis, value in move.items() if axis not in ("x_um", "y_um")})
    return [piece for piece in pieces if piece]


def error_in_units(error: np.ndarray, dofs: Sequence[str]) -> np.ndarray:
    """The error in the tolerances' units: px for translation, degrees for rotation."""
    return np.array([math.degrees(value) if dof == "rotation" else value for dof, value in zip(dofs, error)])


def make_law(name: str, dofs: Sequence[str] = ("x", "y"), *, camera_to_stage: CameraToStage | None = None,
             gain: AdaptiveGain | ExponentialGain | None = None, integral_time_s: float | None = None,
             model_uncertainty: float = 0.15, noise_px: float = 0.03, tolerance_px: float = 0.1,
             tolerance_deg: float = 0.05,
             max_move_um: float = 10.0, max_moves: int = 1, max_turn_deg: float = 5.0,
             creep_per_decade: float = PositionLaw.creep_per_decade,
             partial_frames: bool = False) -> ControlLaw | PositionLaw:
    """The planar law a run's settings name (``law``: one of :data:`LAWS`). Both take
    ``step(dx_px, dy_px, rotation_deg, pixel_size_nm, sampling_time_s)`` on the frames the
    caller acts on and ``applied(move)`` after the stage's reply; each ignores what it
    does not need (the paper's law the saturation and tolerances, the caller saturates;
    the position law the gain and the integral)."""
    camera_to_stage = camera_to_stage or CameraToStage()
    if name == "paper":
        return ControlLaw(tuple(dofs), gain or AdaptiveGain(), camera_to_stage, integral_time_s=integral_time_s)
    if name == "position":
        return PositionLaw(tuple(dofs), camera_to_stage, model_uncertainty=model_uncertainty, noise_px=noise_px,
                           tolerance_px=tolerance_px, tolerance_deg=tolerance_deg, max_move_um=max_move_um,
                           max_moves=max_moves, max_turn_deg=max_turn_deg, creep_per_decade=creep_per_decade,
                           partial_frames=partial_frames)
    raise ValueError(f"unknown law {name!r}; laws: {', '.join(LAWS)}")
