"""The REST API (FastAPI), one router per tag over :class:`services.gateway.core.GatewayCore`:
``teach``, ``stage``, ``runs``, ``targets``, ``images``, ``live``; request and response
models from :mod:`semservo.api` (the client's too)."""
