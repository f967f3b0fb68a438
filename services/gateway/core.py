"""The gateway's core: one object that knows every service through small ports, keeps
the latest frame, records runs as their events arrive, and answers what the REST API
asks. No HTTP here (``app.py``) and no sockets of its own (``main.py`` wires them), so
it is tested with the real services and no web server.
"""

from __future__ import annotations

import base64
import io
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np
from PIL import Image

from semservo.control import CameraToStage
from semservo.imagefiles import ImageFileError, read_image, write_image
from semservo.messages import ACQUISITION_FIELDS, ControllerEvent
from semservo.transport import CommandError, ServiceUnavailable
from semservo.wire import Frame
from services.gateway.records import FINISHED, RunStore

log = logging.getLogger("gateway")

#: How long one round of health answers serves /status (seconds).
HEALTH_TTL_S = 0.25

#: The services the gateway reports on, in the order a user reads them.
SERVICE_NAMES = ("fakelab", "imageserver", "estimator", "stage", "controller")

#: How long a teach waits for the frames it asks to average (a system just started has
#: sent fewer); then it is refused with the count.
TEACH_FRAMES_WAIT_S = 30.0

#: How long a jog waits for the stage's rate limit to allow it (seconds).
JOG_RATE_WAIT_S = 1.0

#: How many times a run's truth is asked of a simulated lab that does not answer.
TRUTH_ATTEMPTS = 30

#: How often unfinished records are looked at (``GatewayCore.reconcile``), seconds.
RECONCILE_EVERY_S = 1.0

#: A controller silent this long with a run in ``servoing``: the run is recorded as failed
#: (provisionally: the controller's own record replaces it when it answers again). Its
#: stage's watchdog has held the stage by then.
CONTROLLER_LOST_AFTER_S = 5.0


class Port(Protocol):
    def request(self, command: str, args: dict | None = None) -> dict: ...


class GatewayError(Exception):
    """What the API turns into a 4xx/5xx body: ``status``, machine ``code``, words."""

    def __init__(self, status: int, code: str, message: str, **extra):
        super().__init__(message)
        self.status, self.code, self.message, self.extra = status, code, message, extra


def call(port: Port | None, service: str, command: str, args: dict | None = None) -> dict:
    """A service command, its failures as :class:`GatewayError` naming the service."""
    if port is None:
        raise GatewayError(503, f"{service}_unavailable", f"the {service} service is not configured")
    try:
        return port.request(command, args or {})
    except ServiceUnavailable as error:
        raise GatewayError(503, f"{service}_unavailable", f"the {service} service does not answer: {error}") from None
    except CommandError as error:
        status = 409 if error.code in ("busy",) else 422 if error.code == "bad_request" else 409
        raise GatewayError(status, error.code, f"{service}: {error.message}", service=service) from None


def to_png(pixels: np.ndarray, *, signed: bool = False) -> bytes:
    """An 8-bit PNG for the browser: levels stretched to the 0.5-99.5 % range (a
    difference image is centred on grey, positive brighter)."""
    values = pixels.astype(np.float32)
    if signed:
        scale = float(np.percentile(np.abs(values), 99.5)) or 1.0
        eight = np.clip(128 + 127 * values / scale, 0, 255)
    else:
        low, high = np.percentile(values, (0.5, 99.5))
        eight = np.clip((values - low) * (255.0 / max(float(high - low), 1e-6)), 0, 255)
    buffer = io.BytesIO()
    Image.fromarray(eight.astype(np.uint8)).save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()


def png_b64(pixels: np.ndarray) -> str:
    """Lossless PNG (8 or 16 bit) of pixels, base64, for the estimator's teach upload."""
    if pixels.dtype not in (np.uint8, np.uint16):
        low, high = float(pixels.min()), float(pixels.max())
        pixels = ((pixels - low) * (65535.0 / max(high - low, 1e-6))).astype(np.uint16)
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="PNG")
    return base64.b64encode(buffer.getvalue()).decode()


@dataclass
class FrameRate:
    """Frames per second over the last few seconds."""

    window_s: float = 5.0
    times: deque = field(default_factory=lambda: deque(maxlen=2000))

    def add(self, t: float) -> None:
        self.times.append(t)

    def rate(self, now: float) -> float:
        recent = [t for t in self.times if now - t <= self.window_s]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) / max(recent[-1] - recent[0], 1e-6)


class GatewayCore:
    def __init__(self, ports: dict[str, Port | None], store: RunStore, *,
                 clock: Callable[[], float] = time.monotonic,
                 broadcast: Callable[[dict], None] | None = None, frames_dir: Path | None = None,
                 camera: CameraToStage | None = None):
        self.ports = ports
        self.camera = camera or CameraToStage()
        self.frames_dir = frames_dir  # set: each run's frames are kept there as TIFF with their metadata
        self.store = store
        self.clock = clock
        self.broadcast = broadcast or (lambda message: None)
        self.lock = threading.Lock()
        self.latest: Frame | None = None
        self.frame_rate = FrameRate()
        self.counters: Counter = Counter()
        self.reference_pixels: np.ndarray | None = None
        self.reference: dict | None = None
        self.taught_truth: dict | None = None  # simulated hardware: the true pose of the reference
        self.last_status: dict = {"state": "idle"}
        self.last_estimate: dict | None = None
        self.latencies_ms: deque = deque(maxlen=1000)
        self.health_lock = threading.Lock()
        self._health_cache: tuple[float, dict] = (-1e9, {})
        self.reconcile_lock = threading.Lock()
        self._reconciled_at = -1e9
        self._controller_silent_since: float | None = None
        self._truth_attempts: dict[str, int] = {}
        saved = store.reference()
        if saved is not None:  # a restarted gateway knows the last reference and its truth
            self.reference, self.taught_truth = saved

    # -- streams (called by main's threads) -------------------------------------
    def on_frame(self, frame: Frame) -> None:
        with self.lock:
            self.latest = frame
        self.frame_rate.add(self.clock())
        self.counters["frames"] += 1
        run_id = self.last_status.get("run_id")
        if self.frames_dir is not None and run_id and self.last_status.get("state") == "servoing":
            header = frame.header
            (self.frames_dir / run_id).mkdir(parents=True, exist_ok=True)
            known = {key: getattr(header, key) for key in ACQUISITION_FIELDS if getattr(header, key) is not None}
            write_image(self.frames_dir / run_id / f"{header.seq:08d}.tif", frame.pixels, seq=header.seq,
                        acquired_at_ns=header.acquired_at_ns, **known)
            self.counters["frames_saved"] += 1

    def on_event(self, event: ControllerEvent) -> None:
        """A controller event: recorded (a run's first sight creates its row), then
        passed on to the WebSocket listeners."""
        data, run_id = event.data, event.run_id
        now_ns = time.time_ns()
        if run_id is not None and not self.store.exists(run_id):
            self._record_start(run_id)
        if event.kind == "iteration" and run_id is not None:
            self.store.add_iteration(run_id, data)
            self.counters["iterations"] += 1
            if data.get("latency_ms") is not None:
                self.latencies_ms.append(data["latency_ms"])
            if "error_px" in data:
                self.last_estimate = data
        elif event.kind == "status":
            self.last_status = data
            self.store.add_event(run_id, now_ns, "status", data)
            if run_id is not None and data.get("state") in FINISHED and not self.store.is_complete(run_id):
                self.finish(run_id)
        self.broadcast({"kind": event.kind, "run_id": run_id, "data": data})

    def _record_start(self, run_id: str) -> None:
        try:
            record = call(self.ports.get("controller"), "controller", "run")
        except GatewayError:
            record = {}
        if record.get("id") != run_id:
            record = {"id": run_id, "started_at_ns": time.time_ns(), "settings": {}}
        self.store.start_run(run_id, started_at_ns=record["started_at_ns"], settings=record.get("settings", {}),
                             reference=self.reference if self.reference and
                             self.reference.get("id") == record.get("reference_id") else
                             {"id": record.get("reference_id")})

    def finish(self, run_id: str) -> bool:
        """A run ended: complete its rows from the controller's own record (events can be
        missed on PUB/SUB, and the gateway may have been down). True when recorded."""
        try:
            record = call(self.ports.get("controller"), "controller", "run", {"id": run_id})
        except GatewayError as error:
            log.warning("cannot complete run %s yet: %s", run_id, error.message)
            return False
        return self._complete(run_id, record)

    def _complete(self, run_id: str, record: dict) -> bool:
        """Record a finished run from the controller's record, with the stage command
        log and, on simulated hardware, the truth."""
        if record.get("id") != run_id or not record.get("outcome"):
            return False
        outcome = dict(record["outcome"])
        stage_log = record.get("stage_log", [])
        if outcome.get("stage_log_error"):
            # The controller could not reach the stage when the run ended (the stage was
            # down): the stage keeps its log across restarts, so ask it directly.
            stage_log = self._stage_log(record["started_at_ns"], outcome["finished_at_ns"])
            if stage_log is not None:
                outcome.pop("stage_log_error")
        for iteration in record.get("records", []):
            self.store.add_iteration(run_id, iteration)
        # The final error as the controller judged it: the mean over its last fresh frames.
        judged = [r["mean_error_px"] for r in record.get("records", []) if r.get("mean_error_px") is not None]
        final_error_px = judged[-1] if judged else None
        truth, truth_note, retry = self._true_final_error(record)
        outcome.pop("truth_pending", None)
        if truth_note:
            outcome["truth_unavailable"] = truth_note
            # The lab did not answer (frozen, restarting): asked again by reconcile for
            # a while, then the reason stays.
            attempts = self._truth_attempts.get(run_id, 0) + 1
            self._truth_attempts[run_id] = attempts
            if retry and attempts < TRUTH_ATTEMPTS:
                outcome["truth_pending"] = True
        else:
            outcome.pop("truth_unavailable", None)
        self.store.finish_run(run_id, outcome=outcome, final_error_px=final_error_px,
                              stage_log=stage_log or [], truth=truth)
        log.info("run %s %s after %s iterations", run_id, outcome["state"], outcome["iterations"])
        return True

    def _stage_log(self, since_ns: int, until_ns: int | None = None) -> list[dict] | None:
        try:
            entries = call(self.ports.get("stage"), "stage", "log", {"since_ns": int(since_ns)})["entries"]
        except GatewayError:
            return None
        return [entry for entry in entries if until_ns is None or entry["time_ns"] <= until_ns]

    def reconcile(self, active_run_id: str | None, controller_up: bool) -> None:
        """Complete every record that is not: runs still ``servoing`` here that the
        controller no longer runs (it finished them while we were down, or died and
        recovered them), provisional ones, ones waiting for the truth, and ones missing
        only the stage's log (asked of the stage). A run whose controller stays silent
        is recorded as failed, provisionally."""
        with self.reconcile_lock:
            now = self.clock()
            if now - self._reconciled_at < RECONCILE_EVERY_S:
                return
            self._reconciled_at = now
            if controller_up:
                self._controller_silent_since = None
            elif self._controller_silent_since is None:
                self._controller_silent_since = now
            for run in self.store.incomplete_runs():
                outcome = run["outcome"] or {}
                if run["id"] == active_run_id:
                    continue
                if run["state"] != "servoing" and not (outcome.get("provisional") or outcome.get("truth_pending")):
                    self._complete_stage_log(run)
                elif not controller_up:
                    if run["state"] == "servoing" and now - self._controller_silent_since >= CONTROLLER_LOST_AFTER_S:
                        self._record_failed(run, f"the controller went down mid-run (no answer for "
                                                 f"{now - self._controller_silent_since:.0f} s); the stage's "
                                                 f"watchdog holds the stage", provisional=True)
                else:
                    try:
                        record = call(self.ports.get("controller"), "controller", "run", {"id": run["id"]})
                    except GatewayError as error:
                        if error.code == "no_such_run" and run["state"] == "servoing":
                            self._record_failed(run, "the controller has no record of this run (its records were "
                                                     "lost?)", provisional=False)
                        continue
                    self._complete(run["id"], record)

    def _complete_stage_log(self, run: dict) -> None:
        stage_log = self._stage_log(run["started_at_ns"], run["finished_at_ns"])
        if stage_log is not None:
            outcome = {key: value for key, value in run["outcome"].items() if key != "stage_log_error"}
            self.store.set_stage_log(run["id"], stage_log, outcome)

    def _record_failed(self, run: dict, reason: str, *, provisional: bool) -> None:
        """Record a run the controller cannot finish as failed (``provisional``: the
        controller's own record replaces this one if it comes back)."""
        stage_log = self._stage_log(run["started_at_ns"])
        outcome = {"state": "failed", "reason": reason, "finished_at_ns": time.time_ns(),
                   "iterations": self.store.get_run(run["id"])["iterations"], "provisional": provisional}
        if stage_log is None:
            outcome["stage_log_error"] = "the stage service did not answer"
        self.store.finish_run(run["id"], outcome=outcome, final_error_px=None, stage_log=stage_log or [], truth=None)
        log.error("run %s: %s", run["id"], reason)
        self.broadcast({"kind": "status", "run_id": run["id"], "data": {"state": "failed", "reason": reason,
                                                                         "run_id": run["id"]}})

    def _true_final_error(self, record: dict) -> tuple[dict | None, str | None, bool]:
        """On simulated hardware: the true pose over the scans of the run's last three
        fresh frames (what it judged convergence on) against the true pose over the
        reference's scans, in um and px; or (None, why not, worth asking again)."""
        fakelab = self.ports.get("fakelab")
        fresh = [r for r in record.get("records", []) if r.get("frame_source_interval_s")
                 and not r.get("action", "").startswith("held")]
        scans = [r["frame_source_interval_s"] for r in fresh[-3:]]
        if fakelab is None or not scans:
            return None, None, False
        saved = self.store.reference(record.get("reference_id"))
        taught = saved[1] if saved is not None else None
        if taught is None:
            return None, "no true pose was recorded when the reference was taught", False
        if "unknown" in taught:
            return None, taught["unknown"], False
        try:
            pose = fakelab.request("pose", {"interval_s": [scans[0][0], scans[-1][1]]})
        except ServiceUnavailable as error:
            log.warning("no truth from the fake lab yet: %s", error)
            return None, f"the simulated lab did not answer for the final pose: {error}", True
        except CommandError as error:
            return None, f"the simulated lab refused the final pose: {error.message}", False
        if pose.get("world_id") != taught.get("world_id"):
            return None, ("the simulated lab restarted since the reference was taught: the run's end and its "
                          "reference are in two different simulated worlds"), False
        pixel_um = record["records"][-1]["pixel_size_nm"] / 1000
        error_um = [pose["x_um"] - taught["x_um"], pose["y_um"] - taught["y_um"]]
        # The rotation-and-tilt stage's true angles against the taught ones (degrees).
        angles = {key: pose[key] - taught[key] for key in ("rotation_deg", "tilt_x_deg", "tilt_y_deg")
                  if pose.get(key) is not None and taught.get(key) is not None}
        return ({"error_um": error_um, "error_px": [value / pixel_um for value in error_um],
                 "error_norm_px": float(np.hypot(*error_um) / pixel_um), "pixel_size_um": pixel_um,
                 "error_deg": angles}, None, False)

    # -- teaching -------------------------------------------------------------
    def teach(self, *, frames: int = 1, image: bytes | None = None, mask: bytes | None = None,
              polygon: list | None = None, label: str | None = None, dwell_ns: float | None = None,
              tilts: bool = False) -> dict:
        """Teach the estimator; a refusal keeps the previous reference (the estimator
        installs a new one only when it is built). ``dwell_ns``: scan the reference once
        at that dwell (a slow, high-quality reference, paper case 5)."""
        self._refuse_during_run("teaching a new reference")
        estimator = self.ports.get("estimator")
        call(estimator, "estimator", "health")  # a dead estimator is named in a second, not after the teach timeout
        latest = self.latest
        scanned_interval = None
        acquisition = {} if latest is None else {key: getattr(latest.header, key) for key in ACQUISITION_FIELDS
                                                 if getattr(latest.header, key) is not None}
        if tilts and (image is not None or mask is not None or polygon is not None or dwell_ns is not None):
            raise GatewayError(422, "invalid", "tilts are taught with the live frames (a focus sweep at the taught "
                                               "pose), not with an upload, a mask or a one-off scan", field="tilts")
        if dwell_ns is not None:
            scan = call(self.ports.get("imageserver"), "imageserver", "scan_once", {"dwell_ns": dwell_ns})
            image = base64.b64decode(scan["image_b64"])
            label = label or f"one scan at {dwell_ns:g} ns/px"
            scanned_interval = scan.get("source_interval_s")
        if image is not None or mask is not None:
            try:
                pixels, from_file = read_image(image if image is not None else mask)
            except ImageFileError as error:
                raise GatewayError(422, "unreadable_image", f"the upload is not a readable PNG/TIFF: {error}") from None
            if latest is not None and pixels.shape != latest.pixels.shape:
                raise GatewayError(422, "wrong_size", f"the image is {pixels.shape[1]} x {pixels.shape[0]}, the "
                                                      f"current scan is {latest.pixels.shape[1]} x {latest.pixels.shape[0]}")
            if image is not None:
                result = call(estimator, "estimator", "teach", {"image_b64": png_b64(pixels), "label": label or "upload"})
                reference_pixels = pixels
                acquisition = from_file  # what the uploaded (or scanned) file says of itself
            else:
                result = call(estimator, "estimator", "teach", {"mask_b64": png_b64((pixels > 0).astype(np.uint8) * 255)})
                reference_pixels = latest.pixels if latest is not None else pixels
        elif polygon is not None:
            result = call(estimator, "estimator", "teach", {"polygon": polygon})
            reference_pixels = latest.pixels if latest is not None else None
        else:
            result = self._teach_live(frames, tilts)
            reference_pixels = self.latest.pixels if self.latest is not None else None
        # The acquisition the reference was made at (pixel size, magnification, working
        # distance...), as far as its source knows it: it goes with every run's record.
        result = {**result, "acquisition": acquisition}
        with self.lock:
            self.reference = result
            self.reference_pixels = None if reference_pixels is None else np.array(reference_pixels)
        if image is not None and scanned_interval is None:
            # An uploaded image may have been taken anywhere: where is unknown to the simulator.
            self.taught_truth = {"reference_id": result["id"], "unknown": "the reference is an uploaded image: where "
                                                                          "it was imaged is unknown to the simulator"}
        else:
            self.taught_truth = self._taught_truth({**result, "source_interval_s": scanned_interval}
                                                   if scanned_interval else result)
        self.store.save_reference(result, self.taught_truth, time.time_ns())
        self.counters["references_taught"] += 1
        self.broadcast({"kind": "reference", "run_id": None, "data": result})
        return result

    def _teach_live(self, frames: int, tilts: bool = False) -> dict:
        """Teach from the live frames, waiting (up to ``TEACH_FRAMES_WAIT_S``) for as many
        as asked to average: a system that has just started has sent fewer. With
        ``tilts``, the estimator also sweeps the focus at the taught pose."""
        deadline = self.clock() + TEACH_FRAMES_WAIT_S
        while True:
            try:
                return call(self.ports.get("estimator"), "estimator", "teach",
                            {"frames": frames, **({"tilts": True} if tilts else {})})
            except GatewayError as error:
                if error.code != "not_enough_frames" or self.clock() > deadline:
                    raise
            time.sleep(0.1)

    def _active_run(self, *, controller_required: bool) -> str | None:
        """The run the controller is servoing, if any. A controller that does not answer
        is a 503 when ``controller_required``, else no run (none can move the stage then:
        its watchdog holds it)."""
        try:
            status = call(self.ports.get("controller"), "controller", "status")
        except GatewayError:
            if controller_required:
                raise
            return None
        return status.get("run_id") if status.get("state") == "servoing" else None

    def _refuse_during_run(self, what: str, *, controller_required: bool = False) -> None:
        run_id = self._active_run(controller_required=controller_required)
        if run_id is not None:
            raise GatewayError(409, "run_active", f"{what} is refused while run {run_id} is servoing; "
                                                  f"POST /stop first", run_id=run_id)

    def _taught_truth(self, reference: dict) -> dict | None:
        fakelab = self.ports.get("fakelab")
        if fakelab is None:
            return None
        try:
            scanned = reference.get("source_interval_s")
            if scanned:
                pose = fakelab.request("pose", {"interval_s": scanned})
            else:  # a mask drawn on the live image: the stage stands where it was taught
                now = fakelab.request("pose", {})["t_s"]
                pose = fakelab.request("pose", {"interval_s": [max(now - 0.5, 0.0), now]})
        except (ServiceUnavailable, CommandError):
            return None
        return {"reference_id": reference["id"], "x_um": pose["x_um"], "y_um": pose["y_um"],
                "world_id": pose.get("world_id"),
                **{key: pose[key] for key in ("rotation_deg", "tilt_x_deg", "tilt_y_deg") if key in pose}}

    # -- images ---------------------------------------------------------------
    def latest_png(self) -> bytes:
        frame = self.latest
        if frame is None:
            raise GatewayError(404, "no_frame", "no frame has arrived yet: is the image server running?")
        return to_png(frame.pixels)

    def reference_png(self) -> bytes:
        if self.reference_pixels is None:
            raise GatewayError(404, "no_reference", "no reference taught through the gateway yet")
        return to_png(self.reference_pixels)

    def difference_png(self) -> bytes:
        """I - I* with both levelled to zero mean and unit spread (the SEM's brightness
        and contrast may differ between them)."""
        frame, reference = self.latest, self.reference_pixels
        if frame is None or reference is None:
            raise GatewayError(404, "no_difference", "the difference needs a live frame and a taught reference")
        if frame.pixels.shape != reference.shape:
            raise GatewayError(409, "wrong_size", "the scan changed size since teaching; teach again")

        def levelled(pixels):
            values = pixels.astype(np.float32)
            return (values - values.mean()) / max(float(values.std()), 1e-6)

        return to_png(levelled(frame.pixels) - levelled(reference), signed=True)

    # -- stage and runs -------------------------------------------------------
    def move(self, targets: dict[str, float], relative: bool) -> dict:
        """A jog or move. Refused during a run (it would fight the controller); the stage
        refuses it too while a run's controller has it armed."""
        self._refuse_during_run("moving the stage")
        # The stage's rate rule refuses a step too soon after the last write (a jog
        # right after a run's last move): an operator's jog waits that moment out.
        deadline = self.clock() + JOG_RATE_WAIT_S
        while True:
            try:
                return call(self.ports.get("stage"), "stage", "move", {"targets": targets, "relative": relative,
                                                                        "owner": "gateway"})
            except GatewayError as error:
                if error.code != "rate_limit" or self.clock() > deadline:
                    raise
            time.sleep(0.05)

    def rotate(self, targets: dict[str, float], relative: bool) -> dict:
        """A turn or tilt of the rotation-and-tilt stage, through the stage service (its
        travel, step and owner rules). Refused during a run, as a jog is."""
        self._refuse_during_run("turning the stage")
        return call(self.ports.get("stage"), "stage", "rotate", {"targets": targets, "relative": relative,
                                                                  "owner": "gateway"})

    def center(self, x_px: float, y_px: float) -> dict:
        """Move the stage so the live image's point (x, y) comes to the centre (click to
        move), through the camera-to-stage transform and the frame's pixel size."""
        frame = self.latest
        if frame is None:
            raise GatewayError(409, "no_frame", "no live frame to click on yet")
        rows, cols = frame.pixels.shape
        if not (0 <= x_px < cols and 0 <= y_px < rows):
            # 409, not 422: the point is well formed; the current scan is what it misses.
            raise GatewayError(409, "outside_image", f"({x_px:.1f}, {y_px:.1f}) is outside the current "
                                                     f"{cols} x {rows} image", field="x_px")
        if frame.header.pixel_size_nm is None:
            raise GatewayError(409, "pixel_size_unknown", "the live frames carry no pixel size, so a click cannot "
                                                          "become a stage move: set SEMSERVO_IMAGESERVER__PIXEL_SIZE_NM")
        x_um, y_um = self.camera.stage_move_um(cols / 2 - x_px, rows / 2 - y_px, frame.header.pixel_size_nm)
        return self.move({"x": x_um, "y": y_um}, relative=True)

    def resume(self) -> dict:
        """Let a stopped or held stage move again (a run cannot be active then)."""
        self._refuse_during_run("resuming the stage", controller_required=True)
        return call(self.ports.get("stage"), "stage", "resume")

    def stage_state(self) -> dict:
        return call(self.ports.get("stage"), "stage", "state")

    def start(self, settings: dict, *, resume: bool = False) -> dict:
        """Start a run. A stage an operator stopped stays stopped: the start is refused
        (409 ``stage_stopped``) unless ``resume`` says the operator lets it move again. A
        stage held by its watchdog (a controller died, or the stage service restarted
        mid-run) is claimed by the new run's controller."""
        controller = self.ports.get("controller")
        self._refuse_during_run("starting a run", controller_required=True)
        stage = call(self.ports.get("stage"), "stage", "state")
        if stage.get("state") == "stopped":
            if not resume:
                raise GatewayError(409, "stage_stopped", f"the stage is stopped ({stage.get('reason')}); "
                                                         f"POST /stage/resume first, or start with ?resume=true")
            call(self.ports.get("stage"), "stage", "resume")
        try:
            started = call(controller, "controller", "start", settings)
        except GatewayError as error:
            if error.code == "busy":
                raise GatewayError(409, "run_active", error.message, run_id=call(controller, "controller",
                                                                                 "status").get("run_id")) from None
            raise
        self._record_start(started["run_id"])
        return started

    def stop(self, reason: str) -> dict:
        """Stop at once: the stage first (it refuses moves from then on), then the run."""
        stage_error = None
        try:
            call(self.ports.get("stage"), "stage", "stop", {"reason": reason})
        except GatewayError as error:
            stage_error = error.message
        try:
            status = call(self.ports.get("controller"), "controller", "stop", {"reason": reason})
        except GatewayError as error:
            if stage_error is not None:
                raise GatewayError(503, "stop_failed", f"neither the stage nor the controller answered: "
                                                       f"{stage_error}; {error.message}") from None
            status = {"state": "stopped", "reason": reason, "controller": error.message}
        return {**status, "stage_stopped": stage_error is None, "stage_error": stage_error}

    # -- status ---------------------------------------------------------------
    def health(self, names: tuple[str, ...] = SERVICE_NAMES) -> dict[str, dict]:
        """Every service's health, asked at most every ``HEALTH_TTL_S``: fifty dashboards
        polling /status must not turn into fifty health requests to each service."""
        with self.health_lock:
            cached_at, report = self._health_cache
            if self.clock() - cached_at < HEALTH_TTL_S and set(names) <= set(report) | set(
                    name for name in names if self.ports.get(name) is None):
                return {name: report[name] for name in names if name in report}
            report = self._ask_health(names)
            self._health_cache = (self.clock(), report)
            return report

    def _ask_health(self, names: tuple[str, ...]) -> dict[str, dict]:
        report = {}
        for name in names:
            port = self.ports.get(name)
            if port is None:
                continue
            try:
                health = port.request("health", {})
                report[name] = {"up": True, "state": health["state"], "last_error": health.get("last_error"),
                                "details": health.get("details", {})}
            except ServiceUnavailable as error:
                report[name] = {"up": False, "state": "down", "last_error": str(error), "details": {}}
            except CommandError as error:
                report[name] = {"up": True, "state": "error", "last_error": error.message, "details": {}}
        return report

    def status(self) -> dict:
        services = self.health()
        controller = services.get("controller", {})
        run = controller.get("details", {}) if controller.get("up") else {}
        stage = services.get("stage", {}).get("details", {})
        latencies = np.array(self.latencies_ms) if self.latencies_ms else None
        estimator = services.get("estimator", {}).get("details", {})
        run_id = run.get("run_id")
        if run_id and run.get("state") in FINISHED and not self.store.is_complete(run_id):
            # The run's last event was missed (PUB/SUB drops, or the gateway was down
            # when it ended): complete its record from the controller now.
            if not self.store.exists(run_id):
                self._record_start(run_id)
            self.finish(run_id)
        self.reconcile(run_id if run.get("state") == "servoing" else None, bool(controller.get("up")))
        return {
            "state": run.get("state", "unknown" if not controller.get("up") else "idle"),
            "reason": run.get("reason", ""),
            "run_id": run.get("run_id"),
            "iteration": run.get("iteration", 0),
            "error_px": run.get("error_px"),
            "error_um": run.get("error_um"),
            "mean_error_px": run.get("mean_error_px"),
            "cost": run.get("cost"),
            "rotation_deg": run.get("rotation_deg"),
            "alpha_deg": run.get("alpha_deg"),
            "beta_deg": run.get("beta_deg"),
            "tilt": estimator.get("last_tilt"),
            "last_latency_ms": run.get("last_latency_ms"),
            "latency_p50_ms": None if latencies is None else float(np.percentile(latencies, 50)),
            "latency_p99_ms": None if latencies is None else float(np.percentile(latencies, 99)),
            "estimation_ms": estimator.get("last_estimation_ms"),
            "snr_db": estimator.get("last_snr_db"),
            "frame_rate": round(self.frame_rate.rate(self.clock()), 2),
            "latest_frame_seq": self.latest.header.seq if self.latest is not None else None,
            "frame_acquisition": {} if self.latest is None else {
                key: getattr(self.latest.header, key) for key in ACQUISITION_FIELDS
                if getattr(self.latest.header, key) is not None},
            "reference": self.reference,
            "stage": {"link": stage.get("link"), "state": stage.get("state"), "reason": stage.get("reason"),
                      "voltages": stage.get("voltages"), "positions_um": stage.get("positions_um")},
            "services": {name: {"up": value["up"], "state": value["state"], "last_error": value["last_error"]}
                         for name, value in services.items()},
            "down": [name for name, value in services.items() if not value["up"]],
            "degraded": [name for name, value in services.items() if value["up"] and value["state"] == "degraded"],
        }
