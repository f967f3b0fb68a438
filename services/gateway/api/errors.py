"""Every error as one body, ``{"error": {"code", "message", "field"}}``, its status from
the code (:func:`semservo.errors.http_status`, the one table of it)."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from semservo.errors import CommandError, first_error, http_status


#: Spellings of a non-finite number a request may carry (lower case, no sign).
NON_FINITE = {"nan", "inf", "infinity"}
#: The number errors a non-finite input reads as (pydantic's types): a bound it fails.
NUMBER_BOUNDS = {"less_than", "less_than_equal", "greater_than", "greater_than_equal", "finite_number"}


def error_response(status: int, code: str, message: str, field: str | None = None, **extra) -> JSONResponse:
    return JSONResponse({"error": {"code": code, "message": message, "field": field, **extra}}, status_code=status)


def allowed_methods(request: Request) -> list[str]:
    """The methods the API's schema gives this request's path (what a 405's ``Allow``
    must list)."""
    import re

    matching = []
    for template, operations in request.app.openapi().get("paths", {}).items():
        pattern = "^" + re.sub(r"\\{[^/]+?\\}", "[^/]+", re.escape(template)) + "$"
        if re.match(pattern, request.url.path):
            # A literal path (/targets/import) takes precedence over a template (/targets/{name}).
            matching.append((template.count("{"), {method.upper() for method in operations}))
    fewest = min((parameters for parameters, _ in matching), default=0)
    return sorted(set().union(*(methods for parameters, methods in matching if parameters == fewest)))


def install(app: FastAPI) -> None:
    @app.exception_handler(CommandError)
    async def command_error(_request: Request, error: CommandError) -> JSONResponse:
        extra = {key: value for key, value in error.extra.items() if key != "field"}
        return error_response(http_status(error.code), error.code, error.message, error.extra.get("field"), **extra)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, error: StarletteHTTPException) -> JSONResponse:
        # The framework's own refusals (a body that does not parse, an unknown path, a
        # method a path does not take) in the same envelope as every other error.
        codes = {400: "bad_body", 404: "not_found", 405: "method_not_allowed"}
        response = error_response(error.status_code, codes.get(error.status_code, "http_error"), str(error.detail))
        for name, value in (error.headers or {}).items():
            response.headers[name] = value
        if error.status_code == 405:
            # Every method the path takes (Starlette names only the first route's).
            response.headers["Allow"] = ", ".join(allowed_methods(request))
        return response

    @app.exception_handler(RequestValidationError)
    async def validation_error(_request: Request, error: RequestValidationError) -> JSONResponse:
        first = error.errors()[0]
        if first.get("type") == "json_invalid":  # its location is a character offset, not a field
            detail = (first.get("ctx") or {}).get("error") or first.get("msg", "")
            return error_response(422, "invalid", f"the body is not valid JSON ({detail})", None)
        location = [str(part) for part in first.get("loc", ()) if part not in ("body", "query", "path")]
        message = first.get("msg", "invalid request")
        if first.get("type") in NUMBER_BOUNDS and str(first.get("input", "")).strip().lower().lstrip("+-") in NON_FINITE:
            # A query's "NaN" parses as a float and then reads as out of range: say what
            # is wrong first, the field's bound after ("not a finite number (NaN): Input
            # should be less than or equal to 100000" read as if NaN were too large).
            message = f"{first['input']} is not a finite number; a finite one is expected ({message[:1].lower()}{message[1:]})"
        return error_response(422, "invalid", message, ".".join(location) or None)


__all__ = ["error_response", "first_error", "install"]
