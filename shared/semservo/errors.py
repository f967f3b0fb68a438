"""The one error type of semservo's commands, and what it means over HTTP.

A service that will not do what it is asked raises :class:`CommandError` with a machine
code (``travel_limit``, ``no_reference``, ``run_active``, ...) and words for a person; the
command's reply carries both, the client side raises the same error again, and the
gateway turns the code into an HTTP status through :func:`http_status`, the one table
of it. A peer that does not answer at all is :class:`ServiceUnavailable`, a transport
matter, never a refusal.
"""

from __future__ import annotations

from typing import Any

import pydantic


class CommandError(RuntimeError):
    """A refusal: ``code`` for programs, ``message`` for people, ``extra`` for details a
    caller may use (e.g. ``run_id`` of the run that is in the way).

    ``transient``: the refusal means "ask again shortly" (a teach waiting for frames), a
    normal step of a caller's polling: servers log it at DEBUG, not as a warning."""

    transient = False

    def __init__(self, code: str, message: str, **extra: Any):
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
        self.extra = extra


class BadRequest(CommandError):
    """Arguments a command cannot accept (sent as ``bad_request``)."""

    def __init__(self, message: str, **extra: Any):
        super().__init__("bad_request", message, **extra)


class ServiceUnavailable(RuntimeError):
    """No reply from a service after every try."""


class RequestCancelled(ServiceUnavailable):
    """The caller gave up waiting for a reply (e.g. the service is stopping): for the
    caller, the service did not answer."""


#: Codes that are not the default 409 ("a rule of the system says no now"). Codes ending in
#: ``_unavailable`` are 503 (a service that does not answer).
_STATUS: dict[str, int] = {
    "bad_body": 400,
    "unauthorized": 401,
    "not_found": 404, "no_such_run": 404, "no_such_target": 404, "no_frame": 404, "no_reference": 404,
    "no_difference": 404, "no_reference_image": 404,
    "method_not_allowed": 405,
    "too_large": 413,
    "json_body": 415,
    "bad_request": 422, "invalid": 422, "empty": 422, "unreadable_image": 422, "wrong_size": 422,
    "bad_target_file": 422,
    "stop_failed": 503,
}


def http_status(code: str) -> int:
    """The HTTP status of a refusal's code: 4xx for what the caller can change, 503 for a
    service that does not answer, 409 (conflict with the system's state) otherwise."""
    if code in _STATUS:
        return _STATUS[code]
    if code.endswith("_unavailable"):
        return 503
    return 409


def first_error(error: pydantic.ValidationError, default_field: str = "request") -> tuple[str | None, str]:
    """The first problem of a validation error as (field path, message): what every
    refusal of a malformed request says, on ZeroMQ and HTTP alike."""
    first = error.errors()[0]
    location = [str(part) for part in first.get("loc", ()) if part not in ("body", "query", "path")]
    return (".".join(location) or None), first.get("msg", f"invalid {default_field}")


def describe_validation_error(error: pydantic.ValidationError, default_field: str = "request") -> str:
    """``field: message`` of the first problem (the words of a ``bad_request``)."""
    field, message = first_error(error, default_field)
    return f"{field or default_field}: {message}"
