"""The gateway's core: one object that knows every service through typed ports, keeps the
latest frame, records runs as their events arrive, stores targets, and answers what the
REST API asks. No HTTP here (``api/``) and no sockets of its own (``main.py`` wires
them), so it is tested with the real services, or in-process ports, and no web server.

The reference has one owner: the estimator. The gateway follows it (whoever taught it:
this API, ``semservo teach``, a stored target) and keeps only what it needs to show and
judge it: its pixels for the PNG endpoints and, on simulated hardware, the true pose it
was taught at.
"""

from __future__ import annotations

import base64
import io
import json
import logging
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tifffile
from PIL import Image

from semservo.control import CameraToStage
from semservo.errors import BadRequest, CommandError, ServiceUnavailable
from semservo.estimation.masks import binary_region
from semservo.imagefiles import ImageFileError, read_image, write_image
from semservo.messages import ACQUISITION_FIELDS, ControllerEvent
from semservo.protocol import Command, Port
from semservo.protocol import controller as controller_protocol
from semservo.protocol import estimator as estimator_protocol
from semservo.protocol import fakelab as fakelab_protocol
from semservo.protocol import imageserver as imageserver_protocol
from semservo.protocol import stage as stage_protocol
from semservo.protocol.controller import RunSettings
from semservo.wire import Frame
from services.gateway.records import FINISHED, RunStore


def view_error_px(pose: dict, taught: dict, pixel_um: float) -> tuple[float, float] | None:
    """On simulated hardware with a tilted stage: how far (px) the content at the taught
    view's centre is from the centre now, the error the image shows. It differs from the
    stage's x, y error by the tilt cradle's pivot lever under the residual tilt, which x
    and y make up for. None when neither pose has tilts (then the two are one)."""
    keys = ("rotation_deg", "tilt_x_deg", "tilt_y_deg")
    if not any(pose.get(key) or taught.get(key) for key in keys[1:]):
        return None
    from semservo.simulation import sem  # the simulator's geometry: only where it runs

    def as_pose(values: dict) -> sem.Pose:
        return sem.Pose(x_um=values["x_um"], y_um=values["y_um"], z_um=values.get("z_um") or 0.0,
                        **{key: values.get(key) or 0.0 for key in keys})
    return sem.view_error_px(as_pose(pose), as_pose(taught), pixel_um)

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

#: A stored target's file: a TIFF of the reference's pixels whose description holds the
#: target as JSON under this key.
TARGET_FILE_KEY = "semservo_target"
#: Finished runs' report PNGs kept drawn (:meth:`GatewayCore.run_report`): about 60 kB each.
REPORTS_KEPT = 32


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
        self.reference: dict | None = None  # the estimator's reference, as the gateway last saw it
        self.taught_truth: dict | None = None  # simulated hardware: the true pose of the reference
        self.last_status: dict = {"state": "idle"}
        self.latencies_ms: deque = deque(maxlen=1000)
        self.health_lock = threading.Lock()
        self._health_cache: tuple[float, dict] = (-1e9, {})
        self.reconcile_lock = threading.Lock()
        self.reference_lock = threading.Lock()
        # One teach at a time (a teach, a target's visit from its teach to its start): two
        # at once would each answer 200 while the later one's reference replaced the other's.
        self._teach_lock = threading.Lock()
        self._teaching_what, self._teaching_thread = "", None
        self._reconciled_at = -1e9
        self._controller_silent_since: float | None = None
        self._truth_attempts: dict[str, int] = {}
        self._pending_truth: dict[str, dict] = {}  # a reference taught from a stored target: its target's truth
        self._reports: OrderedDict[tuple, bytes] = OrderedDict()  # finished runs' report PNGs, newest last
        saved = store.reference()
        if saved is not None:  # a restarted gateway knows the last reference and its truth
            self.reference, self.taught_truth = saved

    # -- talking to the services -------------------------------------------------------
    def ask(self, service: str, command: Command, request=None, /, **fields):
        """A service's command, typed; its failures as :class:`CommandError` naming the
        service (``<service>_unavailable`` when it does not answer: a 503)."""
        port = self.ports.get(service)
        if port is None:
            raise CommandError(f"{service}_unavailable", f"the {service} service is not configured")
        try:
            return port.call(command, request, **fields)
        except ServiceUnavailable as error:
            raise CommandError(f"{service}_unavailable", f"the {service} service does not answer: {error}") from None
        except CommandError as error:
            raise CommandError(error.code, f"{service}: {error.message}", service=service, **error.extra) from None

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
        elif event.kind == "status":
            self.last_status = data
            self.store.add_event(run_id, now_ns, "status", data)
            if run_id is not None and data.get("state") in FINISHED and not self.store.is_complete(run_id):
                self.finish(run_id)
        self.broadcast({"kind": event.kind, "run_id": run_id, "data": data})

    # -- run records -----------------------------------------------------------------
    def _controller_record(self, run_id: str | None = None) -> dict:
        reply = self.ask("controller", controller_protocol.RUN, id=run_id)
        return reply.model_dump(mode="json")

    def _record_start(self, run_id: str) -> None:
        try:
            record = self._controller_record()
        except CommandError:
            record = {}
        if record.get("id") != run_id:
            record = {"id": run_id, "started_at_ns": time.time_ns(), "settings": {}}
        reference = self.reference if self.reference and self.reference.get("id") == record.get("reference_id") \
            else {"id": record.get("reference_id")}
        self.store.start_run(run_id, started_at_ns=record["started_at_ns"], settings=record.get("settings") or {},
                             reference=reference)

    def finish(self, run_id: str) -> bool:
        """A run ended: complete its rows from the controller's own record (events can be
        missed on PUB/SUB, and the gateway may have been down). True when recorded."""
        try:
            record = self._controller_record(run_id)
        except CommandError as error:
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
        # The final error as the controller judged it: the position law's estimate, or the
        # paper's law's mean over its last fresh frames.
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
            entries = self.ask("stage", stage_protocol.LOG, since_ns=int(since_ns)).entries
        except CommandError:
            return None
        return [entry.model_dump() for entry in entries if until_ns is None or entry.time_ns <= until_ns]

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
                        record = self._controller_record(run["id"])
                    except CommandError as error:
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
        """On simulated hardware: the true pose over the scans of what the run judged
        convergence on (the paper's law: its last three fresh frames; the position law:
        the fresh frames since its last move, where the stage rests) against the true pose
        over the reference's scans, in um and px; or (None, why not, worth asking again)."""
        records = record.get("records", [])
        fresh = [r for r in records if r.get("frame_source_interval_s") and not r.get("action", "").startswith("held")]
        scans = [r["frame_source_interval_s"] for r in fresh[-3:]]
        if (record.get("settings") or {}).get("law", "paper") == "position":
            moves = [index for index, r in enumerate(records) if r.get("action") == "moved"]
            resting = [r["frame_source_interval_s"] for r in records[moves[-1] + 1 if moves else 0:]
                       if r.get("frame_source_interval_s") and not r.get("action", "").startswith("held: stale")]
            scans = resting[-3:] or scans
        if self.ports.get("fakelab") is None or not scans:
            return None, None, False
        saved = self.store.reference(record.get("reference_id"))
        taught = saved[1] if saved is not None else None
        if taught is None:
            return None, "no true pose was recorded when the reference was taught", False
        if "unknown" in taught:
            return None, taught["unknown"], False
        lab_health = self._health_cache[1].get("fakelab")
        if lab_health is not None and not lab_health["up"]:
            # Known down from the health just asked: not a request timeout inside every
            # /status (the reconcile asks each second; it took /status to 15-27 s).
            return None, f"the simulated lab is down ({lab_health['last_error']}): asked again when it answers", True
        try:
            pose = self.ports["fakelab"].call(fakelab_protocol.POSE, interval_s=[scans[0][0], scans[-1][1]])
        except ServiceUnavailable as error:
            log.warning("no truth from the fake lab yet: %s", error)
            return None, f"the simulated lab did not answer for the final pose: {error}", True
        except CommandError as error:
            return None, f"the simulated lab refused the final pose: {error.message}", False
        pose = pose.model_dump()
        if pose.get("world_id") != taught.get("world_id"):
            return None, ("the simulated lab restarted since the reference was taught: the run's end and its "
                          "reference are in two different simulated worlds"), False
        pixel_um = record["records"][-1]["pixel_size_nm"] / 1000
        error_um = [pose["x_um"] - taught["x_um"], pose["y_um"] - taught["y_um"]]
        # The rotation-and-tilt stage's true angles against the taught ones (degrees).
        angles = {key: pose[key] - taught[key] for key in ("rotation_deg", "tilt_x_deg", "tilt_y_deg")
                  if pose.get(key) is not None and taught.get(key) is not None}
        truth = {"error_um": error_um, "error_px": [value / pixel_um for value in error_um],
                 "error_norm_px": float(np.hypot(*error_um) / pixel_um), "pixel_size_um": pixel_um,
                 "error_deg": angles}
        view = view_error_px(pose, taught, pixel_um)
        if view is not None:
            truth.update(view_error_px=list(view), view_error_norm_px=float(np.hypot(*view)))
        return truth, None, False

    # -- the reference: the estimator's ------------------------------------------------
    def follow_reference(self, described: dict | None) -> None:
        """The estimator's reference (as it describes it) becomes the one the gateway
        shows and judges runs by: its pixels fetched once per reference, its true pose
        recorded (simulated hardware). Whoever taught it: this API, ``semservo teach``,
        a stored target."""
        if not described:
            return
        with self.reference_lock:
            if self.reference is not None and self.reference.get("id") == described["id"] \
                    and self.reference_pixels is not None:
                self.reference = {**self.reference, **described}  # e.g. its tilt sweep's progress
                return
            try:
                image = self.ask("estimator", estimator_protocol.REFERENCE_IMAGE, id=described["id"])
            except CommandError as error:
                log.warning("cannot fetch the reference's pixels: %s", error.message)
                return
            pixels = np.frombuffer(base64.b64decode(image.pixels_b64), dtype=np.dtype(image.dtype)).reshape(image.shape)
            truth = self._pending_truth.pop(described["id"], None) or self._taught_truth(described)
            with self.lock:
                self.reference, self.reference_pixels = dict(described), pixels
                self.taught_truth = truth
            self.store.save_reference(described, truth, described.get("taught_at_ns") or time.time_ns())
            self.counters["references_taught"] += 1
        self.broadcast({"kind": "reference", "run_id": None, "data": described})

    def _taught_truth(self, reference: dict) -> dict | None:
        fakelab = self.ports.get("fakelab")
        if fakelab is None:
            return None
        scanned = reference.get("source_interval_s")
        if reference.get("kind") == "image" and not scanned:
            # An uploaded image may have been taken anywhere: where is unknown to the simulator.
            return {"reference_id": reference["id"], "unknown": "the reference is an uploaded image: where it was "
                                                                "imaged is unknown to the simulator"}
        try:
            if scanned:
                pose = fakelab.call(fakelab_protocol.POSE, interval_s=list(scanned))
            else:  # a mask drawn on the live image: the stage stands where it was taught
                now = fakelab.call(fakelab_protocol.POSE).t_s
                pose = fakelab.call(fakelab_protocol.POSE, interval_s=[max(now - 0.5, 0.0), now])
        except (ServiceUnavailable, CommandError):
            return None
        pose = pose.model_dump()
        return {"reference_id": reference["id"], "x_um": pose["x_um"], "y_um": pose["y_um"],
                "world_id": pose.get("world_id"),
                **{key: pose[key] for key in ("rotation_deg", "tilt_x_deg", "tilt_y_deg") if key in pose}}

    def current_reference(self) -> dict:
        """The taught reference (the estimator's, followed at once)."""
        try:
            described = self.ask("estimator", estimator_protocol.REPORT).reference
        except CommandError:
            described = None
        if described is not None:
            self.follow_reference(described.model_dump(mode="json", exclude_none=True))
        if self.reference is None or described is None:
            raise CommandError("no_reference", "no reference is taught: teach one first (POST /teach)")
        return self.reference

    # -- teaching -------------------------------------------------------------
    def teach(self, *, frames: int = 1, image: bytes | None = None, mask: bytes | None = None,
              polygon: list | None = None, label: str | None = None, dwell_ns: float | None = None,
              tilts: bool = False) -> dict:
        """Teach the estimator; a refusal keeps the previous reference (the estimator
        installs a new one only when it is built). ``dwell_ns``: scan the reference once
        at that dwell (a slow, high-quality reference, paper case 5). ``tilts``: the
        estimator then sweeps the focus at the taught pose, in the background (the
        reference's ``tilt_teach`` says how far)."""
        with self._teaching("teaching", holder="a teach"):
            return self._teach(frames=frames, image=image, mask=mask, polygon=polygon, label=label,
                               dwell_ns=dwell_ns, tilts=tilts)

    @contextmanager
    def _teaching(self, what: str, holder: str) -> Iterator[None]:
        """Hold the teach (for ``holder``, as refusals name it); another teach meanwhile is refused (409
        ``teach_in_progress``), as is a start (:meth:`_refuse_while_teaching`): two teaches
        at once would each answer 200 while the later one's reference replaced the other's
        (a dashboard's double click, two scripts; a teach during a target's visit would
        have its run position on the other reference)."""
        if not self._teach_lock.acquire(blocking=False):
            raise self._teach_in_progress(what)
        try:
            self._teaching_what, self._teaching_thread = holder, threading.get_ident()
            yield
        finally:
            self._teaching_thread = None
            self._teach_lock.release()

    def _refuse_while_teaching(self, what: str) -> None:
        """409 ``teach_in_progress`` while a teach is under way in another request: a run
        started meanwhile would begin on the old reference and fail when the new one came."""
        if self._teach_lock.locked() and self._teaching_thread != threading.get_ident():
            raise self._teach_in_progress(what)

    def _teach_in_progress(self, what: str) -> CommandError:
        return CommandError("teach_in_progress", f"{what} refused: {self._teaching_what or 'a teach'} is under way; "
                                                 "ask again when it has answered")

    def _teach(self, *, frames: int, image: bytes | None, mask: bytes | None, polygon: list | None,
               label: str | None, dwell_ns: float | None, tilts: bool) -> dict:
        self._refuse_during_run("teaching a new reference")
        self.ask("estimator", estimator_protocol.REPORT)  # a dead estimator named in seconds, not after the teach's 60
        latest = self.latest
        if tilts and (image is not None or mask is not None or polygon is not None or dwell_ns is not None):
            raise BadRequest("tilts are taught with the live frames (a focus sweep at the taught pose), not with an "
                             "upload, a mask or a one-off scan", field="tilts")
        scanned_interval = None
        if dwell_ns is not None:
            scan = self.ask("imageserver", imageserver_protocol.SCAN_ONCE, dwell_ns=dwell_ns)
            image = base64.b64decode(scan.image_b64)
            label = label or f"one scan at {dwell_ns:g} ns/px"
            scanned_interval = scan.source_interval_s
        if image is not None or mask is not None:
            try:
                pixels, _ = read_image(image if image is not None else mask)
            except ImageFileError as error:
                raise CommandError("unreadable_image", f"the upload is not a readable PNG/TIFF: {error}") from None
            if latest is not None and pixels.shape != latest.pixels.shape:
                raise CommandError("wrong_size", f"the image is {pixels.shape[1]} x {pixels.shape[0]}, the current "
                                                 f"scan is {latest.pixels.shape[1]} x {latest.pixels.shape[0]}")
            if image is not None:
                # The file goes as it came: its own metadata (pixel size, ...) goes with it.
                reply = self.ask("estimator", estimator_protocol.TEACH, image_b64=base64.b64encode(image).decode(),
                                 label=label or "upload", source_interval_s=scanned_interval)
            else:
                try:
                    region = binary_region(pixels, "the mask upload")
                except ValueError as error:
                    raise BadRequest(str(error), field="mask") from None
                reply = self.ask("estimator", estimator_protocol.TEACH,
                                 mask_b64=png_b64(region.astype(np.uint8) * 255))
        elif polygon is not None:
            reply = self.ask("estimator", estimator_protocol.TEACH, polygon=polygon)
        else:
            reply = self._teach_live(frames, tilts)
        described = reply.model_dump(mode="json", exclude_none=True)
        self.follow_reference(described)
        return self.reference if self.reference and self.reference["id"] == described["id"] else described

    def _teach_live(self, frames: int, tilts: bool = False):
        """Teach from the live frames scanned after the stage's last move had settled,
        waiting (up to ``TEACH_FRAMES_WAIT_S``) for as many as asked to average: a system
        that has just started has sent fewer, and a jog just before the teach makes the
        frames scanned during it unusable (a blend of two views)."""
        deadline = self.clock() + TEACH_FRAMES_WAIT_S
        try:
            settled_at_ns = self.ask("stage", stage_protocol.STATE).settled_at_ns or None
        except (CommandError, ServiceUnavailable):
            settled_at_ns = None  # no stage to ask (an image-only set-up): the newest frames
        while True:
            try:
                return self.ask("estimator", estimator_protocol.TEACH, frames=frames, tilts=tilts,
                                scanned_after_ns=settled_at_ns)
            except CommandError as error:
                if error.code != "not_enough_frames" or self.clock() > deadline:
                    raise
            time.sleep(0.1)

    def _active_run(self, *, controller_required: bool) -> str | None:
        """The run the controller is servoing, if any. A controller that does not answer
        is a 503 when ``controller_required``, else no run (none can move the stage then:
        its watchdog holds it)."""
        try:
            status = self.ask("controller", controller_protocol.STATUS)
        except CommandError:
            if controller_required:
                raise
            return None
        return status.run_id if status.state == "servoing" else None

    def _refuse_during_run(self, what: str, *, controller_required: bool = False) -> None:
        run_id = self._active_run(controller_required=controller_required)
        if run_id is not None:
            raise CommandError("run_active", f"{what} is refused while run {run_id} is servoing; POST /stop first",
                               run_id=run_id)

    def run_report(self, run: dict) -> bytes:
        """A run's report (PNG, :func:`services.gateway.report.report_png`). A finished
        run's is drawn once and kept (the last ``REPORTS_KEPT``): the dashboard and scripts
        ask again, and drawing takes a few tenths of a second of the gateway's CPU. Kept
        under what the picture shows (the run, its state, reason and iterations), so a
        record completed later is drawn anew."""
        from services.gateway.report import report_png

        if run.get("state") not in FINISHED:
            return report_png(run)
        key = (run.get("id"), run.get("state"), run.get("iterations"), (run.get("outcome") or {}).get("reason"),
               len(run.get("trajectory") or []))
        with self.lock:
            kept = self._reports.get(key)
        if kept is None:
            kept = report_png(run)
            with self.lock:
                self._reports[key] = kept
                while len(self._reports) > REPORTS_KEPT:
                    self._reports.popitem(last=False)
        return kept

    # -- stored targets --------------------------------------------------------------
    def save_target(self, name: str, note: str = "", replace: bool = False) -> dict:
        """The taught reference stored under ``name`` with the stage's pose now and the
        acquisition it was taught at (its pixels, for a run that comes back to it)."""
        reference = self.current_reference()
        if self.reference_pixels is None:
            raise CommandError("no_reference", "the reference's pixels are not here yet; try again in a moment")
        if not replace and self.store.target(name) is not None:
            raise CommandError("target_exists", f"a target {name!r} exists: choose another name, or replace=true",
                               field="name")
        stage = self.ask("stage", stage_protocol.STATE)
        pose = {"positions_um": stage.positions_um, "voltages": stage.voltages,
                "rotation_deg": stage.rotation.angles_deg if stage.rotation else None}
        self.store.save_target(name=name, note=note, created_at_ns=time.time_ns(), reference=reference, stage=pose,
                               acquisition=reference.get("acquisition", {}), truth=self.taught_truth,
                               pixels=self.reference_pixels)
        return self.target(name)

    def target(self, name: str) -> dict:
        target = self.store.target(name)
        if target is None:
            raise CommandError("no_such_target", f"no stored target {name!r}", field="name")
        return target

    def target_pixels(self, name: str) -> np.ndarray:
        pixels = self.store.target_pixels(name)
        if pixels is None:
            raise CommandError("no_such_target", f"no stored target {name!r}", field="name")
        return pixels

    def export_target(self, name: str) -> bytes:
        """A stored target as one file: a TIFF of its reference's pixels, the target (its
        stage pose, acquisition, reference) as JSON in the TIFF's description."""
        target, pixels = self.target(name), self.target_pixels(name)
        saved = {key: target[key] for key in ("name", "note", "created_at_ns", "reference", "stage", "acquisition")}
        buffer = io.BytesIO()
        tifffile.imwrite(buffer, pixels, description=json.dumps({TARGET_FILE_KEY: saved}), metadata=None)
        return buffer.getvalue()

    def import_target(self, data: bytes, *, name: str | None = None, replace: bool = False) -> dict:
        """A target from a file :meth:`export_target` wrote (another gateway's, days ago)."""
        try:
            with tifffile.TiffFile(io.BytesIO(data)) as tiff:
                pixels = tiff.pages[0].asarray()
                saved = json.loads(tiff.pages[0].description)[TARGET_FILE_KEY]
        except (ValueError, KeyError, TypeError, IndexError, tifffile.TiffFileError) as error:
            raise CommandError("bad_target_file", f"not a semservo target file (a TIFF from GET "
                                                  f"/targets/NAME/export): {type(error).__name__}: {error}") from None
        name = name or saved.get("name")
        if not isinstance(name, str) or not name:
            raise CommandError("bad_target_file", "the target file names no target")
        if not replace and self.store.target(name) is not None:
            raise CommandError("target_exists", f"a target {name!r} exists: replace=true to overwrite it", field="name")
        self.store.save_target(name=name, note=str(saved.get("note", "")), created_at_ns=int(saved["created_at_ns"]),
                               reference=saved["reference"], stage=saved.get("stage", {}),
                               acquisition=saved.get("acquisition", {}), truth=None, pixels=np.asarray(pixels))
        return self.target(name)

    def delete_target(self, name: str) -> dict:
        target = self.target(name)
        self.store.delete_target(name)
        return target

    def go_to_target(self, name: str, settings: dict, *, approach: bool = True, resume: bool = False) -> dict:
        """Back to a stored target: (``approach``) the stage to its stored positions, open
        loop through its model and every rule; its reference taught (the stored image);
        then a run positions on the image."""
        with self._teaching(f"going to target {name!r}", holder=f"a visit to target {name!r} (its teach and start)"):
            return self._go_to_target(name, settings, approach=approach, resume=resume)

    def _go_to_target(self, name: str, settings: dict, *, approach: bool, resume: bool) -> dict:
        target, pixels = self.target(name), self.target_pixels(name)
        self._refuse_during_run(f"going to target {name!r}", controller_required=True)
        latest = self.latest
        if latest is not None and pixels.shape != latest.pixels.shape:
            raise CommandError("wrong_size", f"target {name!r} was taught on a {pixels.shape[1]} x {pixels.shape[0]} "
                                             f"scan; the current scan is {latest.pixels.shape[1]} x "
                                             f"{latest.pixels.shape[0]}: set the scan as it was "
                                             f"({target['acquisition']})")
        self._check_stage_may_move(resume)
        if approach and target["stage"].get("positions_um"):
            positions = {axis: value for axis, value in target["stage"]["positions_um"].items()}
            self.move(positions, relative=False)
        buffer = io.BytesIO()
        tifffile.imwrite(buffer, pixels, description=json.dumps({"semservo": target["acquisition"]}), metadata=None)
        reply = self.ask("estimator", estimator_protocol.TEACH, image_b64=base64.b64encode(buffer.getvalue()).decode(),
                         label=f"target {name}")
        described = reply.model_dump(mode="json", exclude_none=True)
        truth = self.store.target_truth(name)
        if truth is not None and "unknown" not in truth:
            self._pending_truth[described["id"]] = {**truth, "reference_id": described["id"]}
        self.follow_reference({**described, "target": name})
        return self.start(settings, resume=resume)

    # -- images ---------------------------------------------------------------
    def latest_png(self) -> bytes:
        frame = self.latest
        if frame is None:
            raise CommandError("no_frame", "no frame has arrived yet: is the image server running?")
        return to_png(frame.pixels)

    def reference_png(self) -> bytes:
        self._follow_estimator()
        if self.reference_pixels is None:
            raise CommandError("no_reference", "no reference is taught")
        return to_png(self.reference_pixels)

    def difference_png(self) -> bytes:
        """I - I* with both levelled to zero mean and unit spread (the SEM's brightness
        and contrast may differ between them)."""
        self._follow_estimator()
        frame, reference = self.latest, self.reference_pixels
        if frame is None or reference is None:
            raise CommandError("no_difference", "the difference needs a live frame and a taught reference")
        if frame.pixels.shape != reference.shape:
            raise CommandError("scan_changed", "the scan changed size since teaching; teach again")

        def levelled(pixels):
            values = pixels.astype(np.float32)
            return (values - values.mean()) / max(float(values.std()), 1e-6)

        return to_png(levelled(frame.pixels) - levelled(reference), signed=True)

    def _follow_estimator(self) -> None:
        """The estimator's reference, from its health (cached): a teach by anyone is seen."""
        estimator = self.health(("estimator",)).get("estimator", {})
        described = estimator.get("details", {}).get("reference")
        if isinstance(described, dict):
            self.follow_reference(described)
        elif estimator.get("up") and described is not None:  # "none taught": restarted, or cleared
            with self.lock:
                self.reference, self.reference_pixels = None, None

    # -- stage and runs -------------------------------------------------------
    def move(self, targets: dict[str, float], relative: bool):
        """A jog or move. Refused during a run (it would fight the controller); the stage
        refuses it too while a run's controller has it armed. Refused while a teach averages
        frames (they would blend two views)."""
        self._refuse_while_teaching("moving the stage")
        self._refuse_during_run("moving the stage")
        # The stage's rate rule refuses a step too soon after the last write (a jog
        # right after a run's last move): an operator's jog waits that moment out.
        deadline = self.clock() + JOG_RATE_WAIT_S
        while True:
            try:
                return self.ask("stage", stage_protocol.MOVE, targets=targets, relative=relative, owner="gateway")
            except CommandError as error:
                if error.code != "rate_limit" or self.clock() > deadline:
                    raise
            time.sleep(0.05)

    def rotate(self, targets: dict[str, float], relative: bool):
        """A turn or tilt of the rotation-and-tilt stage, through the stage service (its
        travel, step and owner rules). Refused during a run, as a jog is."""
        self._refuse_while_teaching("turning the stage")
        self._refuse_during_run("turning the stage")
        return self.ask("stage", stage_protocol.ROTATE, targets=targets, relative=relative, owner="gateway")

    def center(self, x_px: float, y_px: float):
        """Move the stage so the live image's point (x, y) comes to the centre (click to
        move), through the camera-to-stage transform and the frame's pixel size."""
        frame = self.latest
        if frame is None:
            raise CommandError("no_live_frame", "no live frame to click on yet")
        rows, cols = frame.pixels.shape
        if not (0 <= x_px < cols and 0 <= y_px < rows):
            # 409, not 422: the point is well formed; the current scan is what it misses.
            raise CommandError("outside_image", f"({x_px:.1f}, {y_px:.1f}) is outside the current {cols} x {rows} "
                                                f"image", field="x_px")
        if frame.header.pixel_size_nm is None:
            raise CommandError("pixel_size_unknown", "the live frames carry no pixel size, so a click cannot become a "
                                                     "stage move: set SEMSERVO_IMAGESERVER__PIXEL_SIZE_NM")
        x_um, y_um = self.camera.stage_move_um(cols / 2 - x_px, rows / 2 - y_px, frame.header.pixel_size_nm)
        return self.move({"x": x_um, "y": y_um}, relative=True)

    def resume(self):
        """Let a stopped or held stage move again (a run cannot be active then)."""
        self._refuse_during_run("resuming the stage", controller_required=True)
        resumed = self.ask("stage", stage_protocol.RESUME)
        self.forget_health()
        return resumed

    def stage_state(self):
        return self.ask("stage", stage_protocol.STATE)

    def _check_stage_may_move(self, resume: bool) -> None:
        """A stage an operator stopped stays stopped unless ``resume`` says the operator
        lets it move again."""
        stage = self.ask("stage", stage_protocol.STATE)
        if stage.state == "stopped":
            if not resume:
                raise CommandError("stage_stopped", f"the stage is stopped ({stage.reason}); POST /stage/resume first, "
                                                    f"or start with ?resume=true")
            self.ask("stage", stage_protocol.RESUME)

    def start(self, settings: dict, *, resume: bool = False) -> dict:
        """Start a run. A stage an operator stopped stays stopped: the start is refused
        (409 ``stage_stopped``) unless ``resume`` says the operator lets it move again. A
        stage held by its watchdog (a controller died, or the stage service restarted
        mid-run) is claimed by the new run's controller."""
        self._refuse_while_teaching("starting a run")
        self._refuse_during_run("starting a run", controller_required=True)
        self._check_stage_may_move(resume)
        run_settings = RunSettings.model_validate_json(json.dumps(settings))
        try:
            started = self.ask("controller", controller_protocol.START, run_settings)
        except CommandError as error:
            if error.code == "busy":
                status = self.ask("controller", controller_protocol.STATUS)
                raise CommandError("run_active", error.message, run_id=status.run_id) from None
            raise
        self._record_start(started.run_id)
        self.forget_health()
        return {"run_id": started.run_id, "state": started.state}

    def stop(self, reason: str) -> dict:
        """Stop at once: the stage first (it refuses moves from then on), then the run."""
        stage_error = None
        try:
            self.ask("stage", stage_protocol.STOP, reason=reason)
        except CommandError as error:
            stage_error = error.message
        try:
            status = self.ask("controller", controller_protocol.STOP, reason=reason).model_dump(mode="json")
        except CommandError as error:
            if stage_error is not None:
                raise CommandError("stop_failed", f"neither the stage nor the controller answered: {stage_error}; "
                                                  f"{error.message}") from None
            status = {"state": "stopped", "reason": reason, "controller": error.message}
        self.forget_health()
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
            fresh = self._ask_health(names)
            self._health_cache = (self.clock(), {**(report if self.clock() - cached_at < HEALTH_TTL_S else {}),
                                                 **fresh})
            return fresh

    def forget_health(self) -> None:
        """Drop the cached health: after a command that changed a service's state (a
        stop, a start, a resume) the next status asks again, so a script that reads the
        status right after its stop sees it (a status served from the cache said
        'servoing' for up to HEALTH_TTL_S after /stop had answered 'stopped')."""
        with self.health_lock:
            self._health_cache = (-1e9, {})

    def _ask_health(self, names: tuple[str, ...]) -> dict[str, dict]:
        from semservo.protocol import HEALTH

        report = {}
        for name in names:
            port = self.ports.get(name)
            if port is None:
                continue
            try:
                health = port.call(HEALTH)
                report[name] = {"up": True, "state": health.state, "last_error": health.last_error,
                                "details": health.details}
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
        estimator = services.get("estimator", {})
        estimator_details = estimator.get("details", {})
        described = estimator_details.get("reference")
        if isinstance(described, dict):
            self.follow_reference(described)
        elif estimator.get("up") and described is not None:
            with self.lock:
                self.reference, self.reference_pixels = None, None
        run_id = run.get("run_id")
        if run_id and run.get("state") in FINISHED and not self.store.is_complete(run_id):
            # The run's last event was missed (PUB/SUB drops, or the gateway was down
            # when it ended): complete its record from the controller now.
            if not self.store.exists(run_id):
                self._record_start(run_id)
            self.finish(run_id)
        self.reconcile(run_id if run.get("state") == "servoing" else None, bool(controller.get("up")))
        latest = self.latest
        return {
            "state": run.get("state", "unknown" if not controller.get("up") else "idle"),
            "reason": run.get("reason", ""),
            "run_id": run.get("run_id"),
            "dofs": run.get("dofs", []),
            "iteration": run.get("iteration", 0),
            "error_px": run.get("error_px"),
            "error_um": run.get("error_um"),
            "mean_error_px": run.get("mean_error_px"),
            "cost": run.get("cost"),
            "rotation_deg": run.get("rotation_deg"),
            "alpha_deg": run.get("alpha_deg"),
            "beta_deg": run.get("beta_deg"),
            "fresh_frames": run.get("fresh_frames", 0),
            "time_to_target_s": run.get("time_to_target_s"),
            "tilt": estimator_details.get("last_tilt"),
            "last_latency_ms": run.get("last_latency_ms"),
            "latency_p50_ms": None if latencies is None else float(np.percentile(latencies, 50)),
            "latency_p99_ms": None if latencies is None else float(np.percentile(latencies, 99)),
            "estimation_ms": estimator_details.get("last_estimation_ms"),
            "snr_db": estimator_details.get("last_snr_db"),
            "frame_rate": round(self.frame_rate.rate(self.clock()), 2),
            "latest_frame_seq": latest.header.seq if latest is not None else None,
            "frame_acquisition": {} if latest is None else {
                key: getattr(latest.header, key) for key in ACQUISITION_FIELDS
                if getattr(latest.header, key) is not None},
            "frame_shape": None if latest is None else list(latest.pixels.shape),
            "reference": self.reference,
            "stage": {"link": stage.get("link"), "state": stage.get("state"), "reason": stage.get("reason"),
                      "voltages": stage.get("voltages"), "positions_um": stage.get("positions_um")},
            "services": {name: {"up": value["up"], "state": value["state"], "last_error": value["last_error"]}
                         for name, value in services.items()},
            "down": [name for name, value in services.items() if not value["up"]],
            "degraded": [name for name, value in services.items() if value["up"] and value["state"] == "degraded"],
        }


def reference_view(reference: dict | None) -> dict | None:
    """A reference as the API shows it (:class:`semservo.api.TeachResult`)."""
    if reference is None:
        return None
    fields = ("id", "kind", "shape", "pixel_size_nm", "taught_at_ns", "acquisition", "tilt", "tilt_teach", "target")
    detail = {key: value for key, value in reference.items() if key not in fields}
    return {**{key: reference[key] for key in fields if reference.get(key) is not None},
            "thumbnail_url": "/reference.png", "detail": detail, "acquisition": reference.get("acquisition") or {}}

