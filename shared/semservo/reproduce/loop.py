"""One positioning trial in process: the simulated lab (its SEM, its piezo stage with
hysteresis, drift and vibration) on a clock that advances by each scan's time, a motion
measurement (:mod:`.methods`) and the paper's control law (:class:`semservo.control.ControlLaw`,
eq. 30-37). Every method closes this same loop, from the same start, on the same frames'
physics; the truth comes from the simulator.

It leaves out the services (sockets, serial line) that the whole-stack benchmarks
(``bench/positioning.py``, ``bench/tilt.py``) include: here the question is what each
method does with the frames, not how fast the wires are.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import cv2
import numpy as np

from semservo.control import AdaptiveGain, ControlLaw
from semservo.reproduce import methods
from semservo.simulation.sem import ScanSettings
from semservo.simulation.world import HOME_VOLTAGE, PRESETS, World
from semservo.stage_model import BranchModel


class ManualClock:
    """Simulated seconds that pass only when told (a scan's time)."""

    def __init__(self):
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@dataclass(frozen=True)
class TrialSettings:
    tolerance_px: float = 0.1
    converge_frames: int = 3
    max_iterations: int = 150
    lost_after: int = 5
    max_move_um: float = 10.0
    reference_frames: int = 4


class Lab:
    """The simulated lab of one case, stepped by hand."""

    def __init__(self, case: str, seed: int, reference_dwell_ns: float | None = None):
        self.preset = PRESETS[case]
        self.clock = ManualClock()
        self.world = World(self.preset, speedup=1.0, seed=seed, clock=self.clock)
        self.settings = ScanSettings(dwell_ns=self.preset.dwell_ns, magnification=self.preset.magnification,
                                     working_distance_um=self.preset.focus_um)
        self.reference_dwell_ns = reference_dwell_ns or self.preset.reference_dwell_ns
        self.models = {0: BranchModel.tritor("x"), 1: BranchModel.tritor("y")}
        for channel, model in self.models.items():
            model.reset(model.position_for(HOME_VOLTAGE))

    @property
    def pixel_um(self) -> float:
        return self.settings.pixel_um

    def scan(self, dwell_ns: float | None = None) -> tuple[np.ndarray, tuple[float, float]]:
        settings = self.settings if dwell_ns is None else replace(self.settings, dwell_ns=dwell_ns)
        pixels, start, end = self.world.scan(settings, wait=False)
        self.clock.t = end + 1e-3
        return pixels, (start, end)

    def true_pose(self, interval: tuple[float, float]) -> np.ndarray:
        samples = [self.world.pose(t) for t in np.linspace(interval[0], interval[1], 32)]
        return np.array([[p.x_um, p.y_um] for p in samples]).mean(axis=0)

    def move(self, dx_um: float, dy_um: float) -> dict[str, float]:
        """A relative stage move through the lab's displacement model, as the stage service makes it."""
        voltages = {}
        for channel, delta in ((0, dx_um), (1, dy_um)):
            model = self.models[channel]
            voltage = float(np.clip(model.voltage_for(model.position_um + delta), -20.0, 120.0))
            self.world.set_voltage(channel, voltage, self.clock.t)
            voltages["xy"[channel]] = voltage
        self.clock.t += 0.01  # the piezo settles in milliseconds
        return voltages


def mask_of(reference: np.ndarray) -> np.ndarray:
    """The paper's case 6: a binary mask of the part by intensity thresholding (Otsu)."""
    eight = cv2.normalize(reference.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    _, mask = cv2.threshold(cv2.GaussianBlur(eight, (0, 0), 2.0), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return mask > 0


def run_trial(case: str, method: str, start_um: tuple[float, float], *, seed: int = 1,
              settings: TrialSettings = TrialSettings(), reference_dwell_ns: float | None = None,
              keep_images: bool = False) -> dict:
    """One trial: teach at home, displace by ``start_um``, servo with ``method`` until the
    mean error of the last frames is under tolerance, the scene is lost, or the
    iteration limit. Returns the outcome, per-iteration records, the true final error
    (um, from the simulator) and, with ``keep_images``, the desired and final images."""
    lab = Lab(case, seed, reference_dwell_ns)
    frames, intervals = zip(*(lab.scan(lab.reference_dwell_ns) for _ in range(settings.reference_frames)))
    reference = np.mean(frames, axis=0, dtype=np.float32)
    taught = lab.true_pose((intervals[0][0], intervals[-1][1]))
    mask = None
    desired = reference
    if lab.preset.mask_reference:
        mask = mask_of(reference)
        desired = mask.astype(np.float32) * 255  # what a baseline sees: the mask itself
    measure = methods.make(method, desired if method != "semservo" else reference, mask=mask)
    lab.move(*start_um)
    law = ControlLaw(("x", "y"), AdaptiveGain(), integral_time_s=10.0)
    pixel_nm = lab.pixel_um * 1000
    records, recent, lost = [], [], 0
    outcome, reason = "failed", f"iteration limit ({settings.max_iterations}) reached"
    frame, interval = lab.scan()
    last_end = None
    for iteration in range(settings.max_iterations):
        measured = measure(frame)
        record = {"iteration": iteration, "compute_ms": measured.compute_ms, "ok": measured.ok}
        if not measured.ok:
            lost += 1
            record["action"] = f"held: {measured.reason}"
            records.append(record)
            if lost >= settings.lost_after:
                outcome, reason = "failed", f"scene lost: {measured.reason}"
                break
            frame, interval = lab.scan()
            continue
        lost = 0
        error_px = math.hypot(measured.dx, measured.dy)
        recent = (recent + [(measured.dx, measured.dy)])[-settings.converge_frames:]
        record.update(dx_px=measured.dx, dy_px=measured.dy, error_px=error_px)
        if len(recent) == settings.converge_frames and math.hypot(*np.mean(recent, axis=0)) <= settings.tolerance_px:
            record["action"] = "within tolerance"
            records.append(record)
            outcome, reason = "converged", ""
            break
        if error_px > 0.45 * frame.shape[1]:
            record["action"] = "held: beyond the field"
            records.append(record)
            outcome, reason = "failed", f"measured {error_px:.0f} px: beyond half the field (lost or diverged)"
            break
        sampling = interval[1] - last_end if last_end is not None else 2 * (interval[1] - interval[0])
        last_end = interval[1]
        step = law.step(measured.dx, measured.dy, 0.0, pixel_nm, sampling)
        move = dict(step.move)
        planar = math.hypot(move["x_um"], move["y_um"])
        if planar > settings.max_move_um:
            move = {key: value * settings.max_move_um / planar for key, value in move.items()}
        record.update(cost=step.cost, gain=step.gain, voltages=lab.move(move["x_um"], move["y_um"]),
                      action="moved")
        records.append(record)
        frame, interval = lab.scan()
    final = lab.true_pose(interval) - taught
    result = {
        "case": case, "method": method, "start_um": list(start_um), "seed": seed, "outcome": outcome,
        "reason": reason, "iterations": sum(1 for r in records if r.get("action") == "moved"), "records": records,
        "true_error_um": final.tolist(), "true_error_px": float(np.hypot(*final) / lab.pixel_um),
        "compute_ms": float(np.mean([r["compute_ms"] for r in records])) if records else None,
        "frame_time_s": lab.settings.frame_time_s, "pixel_um": lab.pixel_um, "settings": asdict(settings),
    }
    if keep_images:
        result["desired"] = desired
        result["final"] = frame
    return result


def rmse_psnr(desired: np.ndarray, final: np.ndarray) -> tuple[float, float]:
    """RMSE and PSNR (dB) between the desired and the final image, 8-bit scale, as the
    paper's Table III (both levelled to the same range first)."""
    a = cv2.normalize(desired.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX)
    b = cv2.normalize(final.astype(np.float32), None, 0, 255, cv2.NORM_MINMAX)
    rmse = float(np.sqrt(np.mean((a - b) ** 2)))
    return rmse, float(20 * math.log10(255.0 / max(rmse, 1e-9)))
