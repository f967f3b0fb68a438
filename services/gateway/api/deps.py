"""What every route depends on: the core, and the bearer token (one check, for HTTP and
for the WebSocket alike)."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request, WebSocket
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from semservo.errors import CommandError
from services.gateway.core import GatewayCore

bearer = HTTPBearer(auto_error=False)


def token_matches(expected: str | None, given: str | None) -> bool:
    """Constant time, so the comparison leaks nothing of the token."""
    return expected is None or hmac.compare_digest((given or "").encode(), expected.encode())


def get_core(request: Request) -> GatewayCore:
    return request.app.state.core


def require_token(request: Request,
                  credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]) -> None:
    """Every state-changing endpoint: the bearer token, when one is configured."""
    if not token_matches(request.app.state.api_token, credentials.credentials if credentials else None):
        raise CommandError("unauthorized", "a valid bearer token is required for this endpoint")


def websocket_token(socket: WebSocket) -> str | None:
    """A WebSocket's token: ``?token=`` (browsers cannot set headers on a WebSocket) or
    the bearer header."""
    header = socket.headers.get("authorization", "")
    return socket.query_params.get("token") or (header[7:] if header.lower().startswith("bearer ") else None)


Core = Annotated[GatewayCore, Depends(get_core)]
