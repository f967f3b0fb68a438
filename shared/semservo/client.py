"""The lab-script client: semservo's REST API from Python, sync and async (httpx).

    from semservo.client import Client

    with Client() as lab:                        # $SEMSERVO_URL, else 127.0.0.1:$SEMSERVO_GATEWAY__HTTP_PORT or :8000
        lab.teach()                              # the live frame is the target
        lab.move(x_um=6, y_um=-4)                # jog away (relative, um)
        run = lab.start(tolerance_px=0.1)        # servo back
        result = lab.wait(run.run_id, timeout=120)
        print(result.state, result.iterations, result.truth)

Every method returns the gateway's own response model (:mod:`semservo.api`: typed,
documented, ``result.state`` and ``result["state"]`` both work). Every failure raises
:class:`SemservoError` (or a subclass) carrying the server's error body: ``status``,
``code`` (machine-readable), ``message`` (words), ``field``.
"""

from __future__ import annotations

import abc
import asyncio
import json
import logging
import math
import os
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from urllib.parse import quote

import httpx
from pydantic import BaseModel, TypeAdapter

from semservo.api import (MoveReply, RotateReply, RunRecord, RunSummary, StageState, StartResult, Status, StopResult,
                          Target, TeachResult, TiltTeach)

DEFAULT_URL = "http://127.0.0.1:8000"


def default_url() -> str:
    """``$SEMSERVO_URL``, else the local gateway on ``$SEMSERVO_GATEWAY__HTTP_PORT`` (the
    port ``semservo up`` and the demo use), else :data:`DEFAULT_URL`."""
    port = os.environ.get("SEMSERVO_GATEWAY__HTTP_PORT")
    return os.environ.get("SEMSERVO_URL") or (f"http://127.0.0.1:{port}" if port else DEFAULT_URL)
FINISHED = ("converged", "failed", "stopped")


log = logging.getLogger("semservo.client")

#: How long a wait that gives up keeps asking a gateway that does not answer to stop its run.
STOP_TRIES_S = 5.0


def _worth_asking_again(error: "SemservoError") -> bool:
    """A wait's poll that may answer next time: the run not recorded yet (404), the
    gateway unreachable or restarting (0, 5xx)."""
    return error.status in (0, 404) or error.status >= 500


class SemservoError(Exception):
    """The gateway said no (4xx/5xx) or could not be reached (status 0)."""

    def __init__(self, status: int, code: str, message: str, field: str | None = None, body: dict | None = None):
        # Status 0 is no answer at all: not shown as if it were an HTTP status.
        super().__init__(f"{f'{status} ' if status else ''}{code}: {message}" + (f" (field {field})" if field else ""))
        self.status, self.code, self.message, self.field, self.body = status, code, message, field, body or {}


class RunActive(SemservoError):
    """409: a run is active (on a start, a teach or a jog); ``run_id`` names it."""

    @property
    def run_id(self) -> str | None:
        return self.body.get("error", {}).get("run_id")


class WaitTimeout(SemservoError):
    """:meth:`Client.wait` gave up: the run had not ended within its timeout."""


#: How long :meth:`Client.teach` waits for each of the taught pose's focus sweeps (teach with
#: tilts: one, or up to the estimator's ``tilt_teach_sweeps`` where one pins the tilts loosely).
SWEEP_WAIT_S = 180.0


def _typed(model, value):
    """The response as its model (a list of them for ``list[...]``)."""
    if isinstance(model, type) and issubclass(model, BaseModel):
        return model.model_validate(value)
    return TypeAdapter(model).validate_python(value)


def _tilt_teach_done(reference: TeachResult) -> TeachResult:
    """A teach with tilts is done when its sweep is; a failed sweep raises, saying why."""
    teach = reference.tilt_teach
    if teach is not None and teach.state == "failed":
        raise SemservoError(409, teach.code or "sweep_failed", f"the reference {reference.id} is taught, but not its "
                            f"tilts: {teach.error}", body={"error": {"code": teach.code, "message": teach.error}})
    return reference


def _raise_for(response: httpx.Response) -> None:
    if response.is_success:
        return
    try:
        body = response.json()
        error = body.get("error", {})
    except (json.JSONDecodeError, AttributeError):
        body, error = {}, {}
    code = error.get("code", "http_error")
    kind = RunActive if code == "run_active" else SemservoError
    raise kind(response.status_code, code, error.get("message", response.text[:200]), error.get("field"), body)


def _headers(token: str | None) -> dict[str, str]:
    token = token if token is not None else os.environ.get("SEMSERVO_API_TOKEN")
    return {"Authorization": f"Bearer {token}"} if token else {}


def _teach_request(frames: int, image: str | Path | bytes | None, mask: str | Path | bytes | None,
                   polygon: list | None, label: str | None, dwell_ns: float | None = None,
                   tilts: bool = False) -> tuple[str, dict]:
    if polygon is not None:
        return "/teach/polygon", {"json": {"polygon": polygon}}
    files, data = {}, {}
    for name, value in (("image", image), ("mask", mask)):
        if value is not None:
            content = value if isinstance(value, (bytes, bytearray)) else Path(value).read_bytes()
            files[name] = (Path(value).name if not isinstance(value, (bytes, bytearray)) else f"{name}.png", content)
    if label:
        data["label"] = label
    params = {"frames": frames} if dwell_ns is None else {"frames": frames, "dwell_ns": dwell_ns}
    if tilts:
        params["tilts"] = "true"
    return "/teach", {"params": params, "files": files or None, "data": data or None}


def _move_body(x_um: float | None, y_um: float | None, relative: bool) -> dict:
    return {"x_um": x_um, "y_um": y_um, "relative": relative}


def _rotate_body(rotation_deg: float | None, tilt_x_deg: float | None, tilt_y_deg: float | None,
                 relative: bool) -> dict:
    body = {"rotation_deg": rotation_deg, "tilt_x_deg": tilt_x_deg, "tilt_y_deg": tilt_y_deg}
    return {**{axis: value for axis, value in body.items() if value is not None}, "relative": relative}


def _auth_only(headers) -> dict[str, str]:
    """The token for a WebSocket handshake (httpx's other defaults, e.g. Connection:
    keep-alive, would break the upgrade)."""
    return {"Authorization": headers["Authorization"]} if "Authorization" in headers else {}


class Call:
    """One request and how its answer reads: ``model`` (a response model, ``list[...]``
    of one, or None for raw bytes)."""

    def __init__(self, method: str, path: str, model=None, **kwargs):
        self.method, self.path, self.model, self.kwargs = method, path, model, kwargs

    def read(self, answer):
        return answer if self.model is None else _typed(self.model, answer)


class _Endpoints(abc.ABC):
    """Every endpoint, written once for both clients: each method hands a :class:`Call`
    to ``_run``, which the synchronous client answers with the response and the asyncio
    client with a coroutine of it."""

    @abc.abstractmethod
    def _run(self, call: Call):
        """The response to ``call`` (or, asyncio, a coroutine of it)."""

    def reference(self) -> TeachResult:
        """The taught reference (whoever taught it), with its focus sweep's progress."""
        return self._run(Call("GET", "/reference", TeachResult))

    def move(self, x_um: float | None = None, y_um: float | None = None, *, relative: bool = True) -> MoveReply:
        """Jog (relative, the default) or move to a position (um), through the stage's rules."""
        return self._run(Call("POST", "/stage/move", MoveReply, json=_move_body(x_um, y_um, relative)))

    def rotate(self, rotation_deg: float | None = None, tilt_x_deg: float | None = None,
               tilt_y_deg: float | None = None, *, relative: bool = True) -> RotateReply:
        """Turn about the beam and/or tilt (degrees), through the stage service's rules."""
        return self._run(Call("POST", "/stage/rotate", RotateReply,
                              json=_rotate_body(rotation_deg, tilt_x_deg, tilt_y_deg, relative)))

    def center(self, x_px: float, y_px: float) -> MoveReply:
        """Click to move: the live image's point (x, y) comes to the centre."""
        return self._run(Call("POST", "/stage/center", MoveReply, json={"x_px": x_px, "y_px": y_px}))

    def stage(self) -> StageState:
        """Positions, voltages, limits, link, watchdog, the rotation stage's angles."""
        return self._run(Call("GET", "/stage", StageState))

    def resume(self) -> StageState:
        """Let a stopped (or watchdog-held) stage move again: the operator's word."""
        return self._run(Call("POST", "/stage/resume", StageState))

    def start(self, *, resume: bool = False, **settings) -> StartResult:
        """Start a run; settings as the API's RunSettings (tolerance_px, dofs, gain, ...).
        A stage an operator stopped stays stopped (409 ``stage_stopped``) unless
        ``resume=True`` lets it move again."""
        return self._run(Call("POST", "/start", StartResult, json=settings,
                              params={"resume": "true"} if resume else None))

    def stop(self, reason: str = "stop requested") -> StopResult:
        """Stop at once: the stage first (it refuses moves until resumed), then the run."""
        return self._run(Call("POST", "/stop", StopResult, json={"reason": reason}))

    def status(self) -> Status:
        return self._run(Call("GET", "/status", Status))

    def runs(self, limit: int = 100) -> list[RunSummary]:
        return self._run(Call("GET", "/runs", list[RunSummary], params={"limit": limit}))

    def run(self, run_id: str) -> RunRecord:
        return self._run(Call("GET", f"/runs/{run_id}", RunRecord))

    def run_csv(self, run_id: str) -> bytes:
        """A run's iterations as CSV (:func:`save` writes it to a file)."""
        return self._run(Call("GET", f"/runs/{run_id}.csv"))

    def run_report(self, run_id: str) -> bytes:
        """A run's report plot, PNG: error, cost, voltages per iteration (Fig. 9)."""
        return self._run(Call("GET", f"/runs/{run_id}/report.png"))

    def save_target(self, name: str, note: str = "", *, replace: bool = False) -> Target:
        """Store the taught reference under ``name``, with the stage's pose and the
        acquisition (to come back to it days later: :meth:`go_to_target`)."""
        return self._run(Call("POST", "/targets", Target, json={"name": name, "note": note, "replace": replace}))

    def targets(self) -> list[Target]:
        """Every stored target, newest first."""
        return self._run(Call("GET", "/targets", list[Target]))

    def target(self, name: str) -> Target:
        return self._run(Call("GET", f"/targets/{quote(name, safe='')}", Target))

    def delete_target(self, name: str) -> Target:
        return self._run(Call("DELETE", f"/targets/{quote(name, safe='')}", Target))

    def go_to_target(self, name: str, *, approach: bool = True, resume: bool = False, **settings) -> StartResult:
        """Back to a stored target: the stage to its stored pose (``approach``, open
        loop), its reference taught, then a positioning run (``settings`` as start's)."""
        return self._run(Call("POST", f"/targets/{quote(name, safe='')}/go", StartResult,
                              json={"approach": approach, "settings": settings},
                              params={"resume": "true"} if resume else None))

    def export_target(self, name: str) -> bytes:
        """A stored target as one file (TIFF; :func:`save` writes it)."""
        return self._run(Call("GET", f"/targets/{quote(name, safe='')}/export"))

    def import_target(self, file: str | Path | bytes, *, name: str | None = None, replace: bool = False) -> Target:
        """A target from a file :meth:`export_target` wrote (this or another lab's)."""
        content = file if isinstance(file, (bytes, bytearray)) else Path(file).read_bytes()
        data = {"replace": "true" if replace else "false", **({"name": name} if name else {})}
        return self._run(Call("POST", "/targets/import", Target, files={"file": ("target.tif", content)}, data=data))

    def _teach_call(self, frames, image, mask, polygon, label, dwell_ns, tilts) -> Call:
        path, kwargs = _teach_request(frames, image, mask, polygon, label, dwell_ns, tilts)
        return Call("POST", path, TeachResult, **kwargs)


def save(content: bytes, path: str | Path) -> Path:
    """Write what :meth:`Client.run_csv`, :meth:`Client.run_report` or
    :meth:`Client.export_target` returned to ``path``."""
    path = Path(path)
    path.write_bytes(content)
    return path


def _checked(call: "Call") -> "Call":
    """``call``, if its JSON body can be sent: NaN and infinity cannot (JSON has no such
    numbers), which would raise a bare ValueError from deep in httpx; the same
    :class:`SemservoError` a gateway answers for a number out of range, nothing sent."""
    body = call.kwargs.get("json")
    if body is not None:
        try:
            json.dumps(body, allow_nan=False)
        except ValueError:
            bad = sorted(key for key, value in (body.items() if isinstance(body, dict) else ())
                         if isinstance(value, float) and not math.isfinite(value))
            raise SemservoError(422, "not_finite", f"{call.method} {call.path}: not a finite number (NaN or infinity)"
                                f"{' in ' + ', '.join(bad) if bad else ''}; nothing was sent",
                                field=bad[0] if len(bad) == 1 else None) from None
    return call


def _no_gateway(url, error: Exception) -> SemservoError:
    """No gateway at ``url`` (REST or the live events): said with how to start one."""
    return SemservoError(0, "unreachable", f"no gateway answers at {url} ({error}): is the system up (./dev up)? "
                                           "Another address: Client(url) or $SEMSERVO_URL")


def _unreachable(client, error: Exception) -> SemservoError:
    return _no_gateway(client.http.base_url, error)


def _answer(response: httpx.Response):
    _raise_for(response)
    return response.json() if response.headers.get("content-type", "").startswith("application/json") \
        else response.content


def _events_failure(http, error: Exception) -> SemservoError:
    """Why ``WS /events`` failed, as a :class:`SemservoError` like every other failure of
    the clients (a script got a bare ConnectionRefusedError, or websockets' InvalidStatus
    for a missing token where REST says 401)."""
    from websockets.exceptions import ConnectionClosedError, InvalidStatus

    url = _events_url(http)
    token_hint = "give the API token: Client(token=...) or $SEMSERVO_API_TOKEN"
    if isinstance(error, InvalidStatus):
        status = error.response.status_code
        return SemservoError(status, "unauthorized" if status in (401, 403) else "refused",
                             f"the gateway refused the live events at {url} (HTTP {status}); {token_hint}")
    if isinstance(error, ConnectionClosedError):
        if error.rcvd is not None and error.rcvd.code == 1008:
            return SemservoError(401, "unauthorized", f"the gateway refused the live events: {error.rcvd.reason}; "
                                                      f"{token_hint}")
        return SemservoError(0, "unreachable", f"the live events from {url} were cut off: {error}")
    return _no_gateway(url, error)


def _events_url(http) -> str:
    return str(http.base_url).replace("http", "ws", 1).rstrip("/") + "/events"


class Client(_Endpoints):
    """Synchronous client. ``token``: the API token (default ``$SEMSERVO_API_TOKEN``)."""

    def __init__(self, url: str | None = None, *, token: str | None = None, timeout: float = 10.0):
        url = url or default_url()
        self.http = httpx.Client(base_url=url, headers=_headers(token), timeout=timeout)

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    def _run(self, call: Call):
        call = _checked(call)
        try:
            response = self.http.request(call.method, call.path, **call.kwargs)
        except httpx.TransportError as error:
            raise _unreachable(self, error) from None
        return call.read(_answer(response))

    def teach(self, *, frames: int = 1, image: str | Path | bytes | None = None, mask: str | Path | bytes | None = None,
              polygon: list | None = None, label: str | None = None, dwell_ns: float | None = None,
              tilts: bool = False, wait: bool = True,
              progress: Callable[[TiltTeach], None] | None = None) -> TeachResult:
        """Teach the live frame (``frames`` > 1 averages that many), one scan at a slow
        ``dwell_ns`` (a high-quality reference), an image file, a mask image, or a
        polygon of corner points [[x, y], ...] on the live frame. ``tilts``: also sweep
        the focus at the taught pose, so runs can servo alpha and beta; the sweeps take
        seconds to minutes and this waits for them unless ``wait=False`` (then
        :meth:`reference` says how far they are), calling ``progress`` with how far they
        are (:class:`semservo.api.TiltTeach`) each time it asks."""
        reference = self._run(self._teach_call(frames, image, mask, polygon, label, dwell_ns, tilts))
        started = time.monotonic()
        while tilts and wait and reference.tilt_teach is not None and reference.tilt_teach.state == "sweeping":
            if progress is not None:
                progress(reference.tilt_teach)
            if time.monotonic() > started + SWEEP_WAIT_S * reference.tilt_teach.sweep:
                raise WaitTimeout(0, "timeout", f"focus sweep {reference.tilt_teach.sweep} of reference "
                                                f"{reference.id} did not end within {SWEEP_WAIT_S:g} s")
            time.sleep(0.25)
            reference = self.reference()
        return _tilt_teach_done(reference) if tilts and wait else reference

    def wait(self, run_id: str, timeout: float = 300.0, poll_s: float = 0.2, *, stop_on_timeout: bool = False
             ) -> RunRecord:
        """Block until the run ends; its full record. :class:`WaitTimeout` otherwise.

        A gateway that does not answer for a while (restarting: unreachable, 5xx) is asked
        again until the deadline. With ``stop_on_timeout`` no run is left behind: at the
        deadline, or when the wait ends in any error (Ctrl-C included), the run is stopped
        if it is the one servoing (never another script's), and the error says so."""
        deadline = time.monotonic() + timeout
        try:
            while True:  # asked at least once, whatever the timeout
                try:
                    run = self.run(run_id)
                    if run.state in FINISHED:
                        return run
                except SemservoError as error:
                    # A 404 is a run started but not recorded yet (the gateway records a run
                    # at its first event) only if the status names it; else nobody started
                    # it (a typo waited out a 300 s timeout).
                    if not _worth_asking_again(error) or (error.status == 404 and self._current_run_id() != run_id):
                        raise
                if time.monotonic() + poll_s >= deadline:
                    break
                time.sleep(poll_s)
        except BaseException:
            if stop_on_timeout:
                self._stop_if_active(run_id, f"the script waiting for run {run_id} ended in an error")
            raise
        said = self._stop_if_active(run_id, f"the script gave up waiting for run {run_id} after {timeout:g} s") \
            if stop_on_timeout else ""
        raise WaitTimeout(0, "timeout", f"run {run_id} did not end within {timeout:g} s" + said)

    def _current_run_id(self) -> str | None:
        """The run the status names (the active or last one); None if it cannot be told."""
        try:
            return self.status().run_id
        except SemservoError:
            return None

    def _stop_if_active(self, run_id: str, reason: str) -> str:
        """Stop the run if it is the one servoing (never another script's), asking for up
        to :data:`STOP_TRIES_S` while the gateway does not answer; what happened, in words
        (logged as an error when the stop could not be made: the run may still be going)."""
        deadline = time.monotonic() + STOP_TRIES_S
        while True:
            try:
                status = self.status()
                if status.run_id != run_id or status.state != "servoing":
                    return "; it was not servoing, so not stopped"
                self.stop(reason)
                return "; it was stopped"
            except SemservoError as error:
                if not _worth_asking_again(error) or time.monotonic() > deadline:
                    log.error("could not stop run %s: %s", run_id, error)
                    return f"; it could NOT be stopped ({error}): it may still be servoing"
            time.sleep(0.25)

    def events(self, quiet_s: float | None = None) -> Iterator[dict | None]:
        """Live events from ``WS /events``: first ``hello`` (the status as it is), then
        status, iteration and reference events as they happen. With ``quiet_s``, None
        after that many seconds without one, so a loop can look at its clock or the
        status (after a run ends no events come; a lost one is never sent again)."""
        from websockets.exceptions import ConnectionClosedError, ConnectionClosedOK, InvalidHandshake
        from websockets.sync.client import connect

        try:
            with connect(_events_url(self.http), additional_headers=_auth_only(self.http.headers)) as socket:
                while True:
                    try:
                        message = socket.recv(timeout=quiet_s)
                    except TimeoutError:
                        yield None
                        continue
                    except ConnectionClosedOK:  # the gateway said goodbye (it is stopping)
                        return
                    yield json.loads(message)
        except (OSError, InvalidHandshake, ConnectionClosedError) as error:
            raise _events_failure(self.http, error) from None


class AsyncClient(_Endpoints):
    """The same API for asyncio scripts: every method is awaited."""

    def __init__(self, url: str | None = None, *, token: str | None = None, timeout: float = 10.0):
        url = url or default_url()
        self.http = httpx.AsyncClient(base_url=url, headers=_headers(token), timeout=timeout)

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    async def close(self) -> None:
        await self.http.aclose()

    async def _run(self, call: Call):
        call = _checked(call)
        try:
            response = await self.http.request(call.method, call.path, **call.kwargs)
        except httpx.TransportError as error:
            raise _unreachable(self, error) from None
        return call.read(_answer(response))

    async def teach(self, *, frames: int = 1, image=None, mask=None, polygon: list | None = None,
                    label: str | None = None, dwell_ns: float | None = None, tilts: bool = False,
                    wait: bool = True, progress: Callable[[TiltTeach], None] | None = None) -> TeachResult:
        """As :meth:`Client.teach`."""
        reference = await self._run(self._teach_call(frames, image, mask, polygon, label, dwell_ns, tilts))
        started = time.monotonic()
        while tilts and wait and reference.tilt_teach is not None and reference.tilt_teach.state == "sweeping":
            if progress is not None:
                progress(reference.tilt_teach)
            if time.monotonic() > started + SWEEP_WAIT_S * reference.tilt_teach.sweep:
                raise WaitTimeout(0, "timeout", f"focus sweep {reference.tilt_teach.sweep} of reference "
                                                f"{reference.id} did not end within {SWEEP_WAIT_S:g} s")
            await asyncio.sleep(0.25)
            reference = await self.reference()
        return _tilt_teach_done(reference) if tilts and wait else reference

    async def wait(self, run_id: str, timeout: float = 300.0, poll_s: float = 0.2, *,
                   stop_on_timeout: bool = False) -> RunRecord:
        """As :meth:`Client.wait`."""
        deadline = time.monotonic() + timeout
        try:
            while True:  # asked at least once, whatever the timeout
                try:
                    run = await self.run(run_id)
                    if run.state in FINISHED:
                        return run
                except SemservoError as error:
                    if not _worth_asking_again(error) or (error.status == 404
                                                          and await self._current_run_id() != run_id):
                        raise
                if time.monotonic() + poll_s >= deadline:
                    break
                await asyncio.sleep(poll_s)
        except BaseException:
            if stop_on_timeout:
                await self._stop_if_active(run_id, f"the script waiting for run {run_id} ended in an error")
            raise
        said = await self._stop_if_active(run_id, f"the script gave up waiting for run {run_id} after {timeout:g} s") \
            if stop_on_timeout else ""
        raise WaitTimeout(0, "timeout", f"run {run_id} did not end within {timeout:g} s" + said)

    async def _current_run_id(self) -> str | None:
        """As :meth:`Client._current_run_id`."""
        try:
            return (await self.status()).run_id
        except SemservoError:
            return None

    async def _stop_if_active(self, run_id: str, reason: str) -> str:
        """As :meth:`Client._stop_if_active`."""
        deadline = time.monotonic() + STOP_TRIES_S
        while True:
            try:
                status = await self.status()
                if status.run_id != run_id or status.state != "servoing":
                    return "; it was not servoing, so not stopped"
                await self.stop(reason)
                return "; it was stopped"
            except SemservoError as error:
                if not _worth_asking_again(error) or time.monotonic() > deadline:
                    log.error("could not stop run %s: %s", run_id, error)
                    return f"; it could NOT be stopped ({error}): it may still be servoing"
            await asyncio.sleep(0.25)

    async def events(self, quiet_s: float | None = None) -> AsyncIterator[dict | None]:
        """As :meth:`Client.events`."""
        from websockets.asyncio.client import connect
        from websockets.exceptions import ConnectionClosedError, ConnectionClosedOK, InvalidHandshake

        try:
            async with connect(_events_url(self.http), additional_headers=_auth_only(self.http.headers)) as socket:
                while True:
                    try:
                        message = await asyncio.wait_for(socket.recv(), quiet_s)
                    except TimeoutError:
                        yield None
                        continue
                    except ConnectionClosedOK:  # the gateway said goodbye (it is stopping)
                        return
                    yield json.loads(message)
        except (OSError, InvalidHandshake, ConnectionClosedError) as error:
            raise _events_failure(self.http, error) from None
