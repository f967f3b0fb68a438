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
    (:class:`ControlLaw`, :class:`TiltLaw`, :class:`semservo.position_law.PositionLaw`)."""

    error: tuple[float, ...]  # e = s - s* (eq. 31) in the law's units (px, rad)
    cost: float  # C = e^T e (eq. 32)
    gain: float  # lambda (eq. 35), after the no-overshoot cap
    velocity: tuple[float, ...]  # eq. 36
    move: dict[str, float]  # stage displacement by axis: "x_um", "y_um", "rotation_deg", "tilt_x_deg", "tilt_y_deg"
    integral: tuple[float, ...] | None = None

    @classmethod
    def idle(cls) -> "LawStep":
        """Nothing to do (e.g. a tilts-only run between two focus sweeps)."""
        return cls(error=(), cost=0.0, gain=0.0, velocity=(), move={})


def velocity_and_displacement(error: np.ndarray, interaction: np.ndarray, gain: float, sampling_time_s: float,
                              previous_velocity: np.ndarray | None) -> tuple[float, np.ndarray, np.ndarray]:
    """The sequence both of the paper's laws share: the gain capped for the sampling
    time, the velocity (eq. 36) and the displacement over the sampling time (eq. 37,
    from the previous velocity, or the current one on the first iteration).

    Eq. 37 scales the move with the sampling time, so a slow image source (or a
    sped-up simulation that renders slower than it scans) would overshoot: the gain is
    capped where the loop stops approaching monotonically. Returns (gain, velocity,
    displacement)."""
    gain = min(gain, NO_OVERSHOOT_GAIN_TIMES_T / max(sampling_time_s, 1e-6))
    velocity = levenberg_marquardt_velocity(error, interaction, gain)
    previous = previous_velocity if previous_velocity is not None else velocity
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

    def reset(self) -> None:
        self.previous_velocity = None
        self.integral = None

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
             sampling_time_s: float) -> LawStep:
        """Error, cost, gain, camera velocity (eq. 30-36) and the stage displacement
        (eq. 37): ``move`` has "x_um", "y_um", "rotation_deg" for the chosen DOFs."""
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

    def reset(self) -> None:
        self.previous_velocity = None

    def step(self, alpha_deg: float, beta_deg: float, sampling_time_s: float) -> LawStep:
        """Error (rad), cost, gain, velocity (rad/s) and the stage's tilt move (degrees,
        ``move`` has "tilt_x_deg", "tilt_y_deg" for the chosen DOFs)."""
        from semservo.estimation.tilt import tilt_rotation  # the convention lives there

        unknown = set(self.dofs) - set(TILT_DEGREES_OF_FREEDOM)
        if unknown:
            raise ValueError(f"unknown tilt degrees of freedom {sorted(unknown)}")
        vector = theta_u(tilt_rotation(alpha_deg if "alpha" in self.dofs else 0.0,
                                       beta_deg if "beta" in self.dofs else 0.0))
        theta = float(np.linalg.norm(vector))
        full = theta_u_interaction(theta, vector if theta > 0 else (1.0, 0.0, 0.0))
        index = [TILT_DEGREES_OF_FREEDOM.index(dof) for dof in self.dofs]
        error = vector[index]
        interaction = full[np.ix_(index, index)]
        gain, velocity, moved = velocity_and_displacement(error, interaction, self.gain(np.degrees(error)),
                                                          sampling_time_s, self.previous_velocity)
        self.previous_velocity = velocity
        move = self.camera_to_stage.stage_move(dict(zip(self.dofs, moved)))
        return LawStep(_floats(error), cost(error), gain, _floats(velocity), move)
