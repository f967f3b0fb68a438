"""A stop's body is read leniently (services/gateway/api/runs.py): whatever arrives, a
reason the services' messages can carry comes out, and what was not used is said."""

from __future__ import annotations

import json

import pytest

from semservo.protocol import controller as controller_protocol
from services.gateway.api.runs import STOP_REASON_CHARS, stop_reason


@pytest.mark.parametrize("body, reason, said", [
    (b"", "stop requested", None),
    (b"null", "stop requested", None),
    (b'{"reason": "operator: sample loose"}', "operator: sample loose", None),
    (b'{"reason": null}', "stop requested", None),
    (b'{"reason": 123}', "stop requested", "not a string"),
    (b'{"reasn": "typo"}', "stop requested", "unknown fields ignored: reasn"),
    (b"not json", "stop requested", "not JSON"),
    (b"[1, 2]", "stop requested", "not a JSON object"),
    (b"[" * 5000, "stop requested", "not JSON"),  # deeper than the parser goes: RecursionError
    (b'{"reason": "\\ud800 x"}', "? x", "characters that are not text replaced"),  # a lone surrogate: valid JSON, not UTF-8
    (b'{"reason": "  two\\nlines  "}', "two lines", None),
])
def test_every_body_gives_a_reason_the_services_can_carry(body, reason, said):
    got, problem = stop_reason(body)
    assert got == reason
    assert (problem is None) if said is None else (said in problem), problem
    # The stage's and the controller's stop take it (it once made both refuse, nothing stopped).
    controller_protocol.STOP.build(reason=got)


def test_a_long_reason_is_cut_not_refused():
    got, problem = stop_reason(json.dumps({"reason": "x" * 1000}).encode())
    assert len(got) == STOP_REASON_CHARS and got.endswith("…") and "cut to" in problem
