"""The lab-script client: semservo's REST API from Python, sync and async (httpx).

    from semservo.client import Client

    with Client() as lab:                        # $SEMSERVO_URL, else http://127.0.0.1:8000
        lab.teach()                              # the live frame is the target
        lab.move(x_um=6, y_um=-4)                # jog away (relative, um)
        run = lab.start(tolerance_px=0.1)        # servo back
        result = lab.wait(run["run_id"], timeout=120)
        print(result["state"], result["iterations"], result["truth"])

Every failure raises :class:`SemservoError` (or a subclass) carrying the server's error
body: ``status``, ``code`` (machine-readable), ``message`` (words), ``field``.
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import httpx

DEFAULT_URL = "http://127.0.0.1:8000"
FINISHED = ("converged", "failed", "stopped")


class SemservoError(Exception):
    """The gateway said no (4xx/5xx) or could not be reached (status 0)."""

    def __init__(self, status: int, code: str, message: str, field: str | None = None, body: dict | None = None):
        super().__init__(f"{status} {code}: {message}" + (f" (field {field})" if field else ""))
        self.status, self.code, self.message, self.field, self.body = status, code, message, field, body or {}


class RunActive(SemservoError):
    """409 on start: a run is active; ``run_id`` names it."""

    @property
    def run_id(self) -> str | None:
        return self.body.get("error", {}).get("run_id")


class WaitTimeout(SemservoError):
    """:meth:`Client.wait` gave up: the run had not ended within its timeout."""


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
    # A teach with tilts waits for a focus sweep: seconds to a minute of scans.
    extra = {"timeout": 150.0} if tilts else {}
    return "/teach", {"params": params, "files": files or None, "data": data or None, **extra}


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


class Client:
    """Synchronous client. ``token``: the API token (default ``$SEMSERVO_API_TOKEN``)."""

    def __init__(self, url: str | None = None, *, token: str | None = None, timeout: float = 10.0):
        url = url or os.environ.get("SEMSERVO_URL", DEFAULT_URL)
        self.http = httpx.Client(base_url=url, headers=_headers(token), timeout=timeout)

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    def _call(self, method: str, path: str, **kwargs) -> Any:
        try:
            response = self.http.request(method, path, **kwargs)
        except httpx.TransportError as error:
            raise SemservoError(0, "unreachable", f"{self.http.base_url}: {error}") from None
        _raise_for(response)
        return response.json() if response.headers.get("content-type", "").startswith("application/json") \
            else response.content

    def teach(self, *, frames: int = 1, image: str | Path | bytes | None = None, mask: str | Path | bytes | None = None,
              polygon: list | None = None, label: str | None = None, dwell_ns: float | None = None,
              tilts: bool = False) -> dict:
        """Teach the live frame (``frames`` > 1 averages that many), one scan at a slow
        ``dwell_ns`` (a high-quality reference), an image file, a mask image, or a
        polygon of corner points [[x, y], ...] on the live frame. ``tilts``: also sweep
        the focus at the taught pose, so runs can servo alpha and beta."""
        path, kwargs = _teach_request(frames, image, mask, polygon, label, dwell_ns, tilts)
        return self._call("POST", path, **kwargs)

    def move(self, x_um: float | None = None, y_um: float | None = None, *, relative: bool = True) -> dict:
        return self._call("POST", "/stage/move", json=_move_body(x_um, y_um, relative))

    def rotate(self, rotation_deg: float | None = None, tilt_x_deg: float | None = None,
               tilt_y_deg: float | None = None, *, relative: bool = True) -> dict:
        """Turn about the beam and/or tilt (degrees), through the stage service's rules."""
        return self._call("POST", "/stage/rotate", json=_rotate_body(rotation_deg, tilt_x_deg, tilt_y_deg, relative))

    def stage(self) -> dict:
        return self._call("GET", "/stage")

    def start(self, *, resume: bool = False, **settings) -> dict:
        """Start a run; settings as the API's RunSettings (tolerance_px, dofs, gain, ...).
        A stage an operator stopped stays stopped (409 ``stage_stopped``) unless
        ``resume=True`` lets it move again."""
        return self._call("POST", "/start", json=settings, params={"resume": "true"} if resume else None)

    def stop(self, reason: str = "stop requested") -> dict:
        return self._call("POST", "/stop", json={"reason": reason})

    def status(self) -> dict:
        return self._call("GET", "/status")

    def runs(self, limit: int = 100) -> list[dict]:
        return self._call("GET", "/runs", params={"limit": limit})

    def run(self, run_id: str) -> dict:
        return self._call("GET", f"/runs/{run_id}")

    def wait(self, run_id: str, timeout: float = 300.0, poll_s: float = 0.2) -> dict:
        """Block until the run ends; its full record. :class:`WaitTimeout` otherwise."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            run = self._finished(run_id)
            if run is not None:
                return run
            time.sleep(poll_s)
        raise WaitTimeout(0, "timeout", f"run {run_id} did not end within {timeout:g} s")

    def _finished(self, run_id: str) -> dict | None:
        try:
            run = self.run(run_id)
        except SemservoError as error:
            if error.status == 404:  # not recorded yet
                return None
            raise
        return run if run["state"] in FINISHED else None

    def events(self) -> Iterator[dict]:
        """Live events (status, iteration, reference) from ``WS /events``."""
        from websockets.sync.client import connect

        url = str(self.http.base_url).replace("http", "ws", 1).rstrip("/") + "/events"
        with connect(url, additional_headers=_auth_only(self.http.headers)) as socket:
            for message in socket:
                yield json.loads(message)


class AsyncClient:
    """The same API for asyncio scripts."""

    def __init__(self, url: str | None = None, *, token: str | None = None, timeout: float = 10.0):
        url = url or os.environ.get("SEMSERVO_URL", DEFAULT_URL)
        self.http = httpx.AsyncClient(base_url=url, headers=_headers(token), timeout=timeout)

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    async def close(self) -> None:
        await self.http.aclose()

    async def _call(self, method: str, path: str, **kwargs) -> Any:
        try:
            response = await self.http.request(method, path, **kwargs)
        except httpx.TransportError as error:
            raise SemservoError(0, "unreachable", f"{self.http.base_url}: {error}") from None
        _raise_for(response)
        return response.json() if response.headers.get("content-type", "").startswith("application/json") \
            else response.content

    async def teach(self, *, frames: int = 1, image=None, mask=None, polygon: list | None = None,
                    label: str | None = None, dwell_ns: float | None = None, tilts: bool = False) -> dict:
        path, kwargs = _teach_request(frames, image, mask, polygon, label, dwell_ns, tilts)
        return await self._call("POST", path, **kwargs)

    async def move(self, x_um: float | None = None, y_um: float | None = None, *, relative: bool = True) -> dict:
        return await self._call("POST", "/stage/move", json=_move_body(x_um, y_um, relative))

    async def rotate(self, rotation_deg: float | None = None, tilt_x_deg: float | None = None,
                     tilt_y_deg: float | None = None, *, relative: bool = True) -> dict:
        """Turn about the beam and/or tilt (degrees), through the stage service's rules."""
        return await self._call("POST", "/stage/rotate",
                                json=_rotate_body(rotation_deg, tilt_x_deg, tilt_y_deg, relative))

    async def stage(self) -> dict:
        return await self._call("GET", "/stage")

    async def start(self, *, resume: bool = False, **settings) -> dict:
        return await self._call("POST", "/start", json=settings, params={"resume": "true"} if resume else None)

    async def stop(self, reason: str = "stop requested") -> dict:
        return await self._call("POST", "/stop", json={"reason": reason})

    async def status(self) -> dict:
        return await self._call("GET", "/status")

    async def runs(self, limit: int = 100) -> list[dict]:
        return await self._call("GET", "/runs", params={"limit": limit})

    async def run(self, run_id: str) -> dict:
        return await self._call("GET", f"/runs/{run_id}")

    async def wait(self, run_id: str, timeout: float = 300.0, poll_s: float = 0.2) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                run = await self.run(run_id)
                if run["state"] in FINISHED:
                    return run
            except SemservoError as error:
                if error.status != 404:
                    raise
            await asyncio.sleep(poll_s)
        raise WaitTimeout(0, "timeout", f"run {run_id} did not end within {timeout:g} s")

    async def events(self) -> AsyncIterator[dict]:
        from websockets.asyncio.client import connect

        url = str(self.http.base_url).replace("http", "ws", 1).rstrip("/") + "/events"
        async with connect(url, additional_headers=_auth_only(self.http.headers)) as socket:
            async for message in socket:
                yield json.loads(message)
