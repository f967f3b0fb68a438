"""The paper's experiments with its baselines, beside its numbers (``semservo reproduce``).

``./dev bench reproduce`` is the same as ``semservo reproduce``; options pass through (``--quick``, ``--only``,
``--fresh``, ``--out``)."""

from __future__ import annotations

import sys

from semservo.cli import main

if __name__ == "__main__":
    raise SystemExit(main(["reproduce", *sys.argv[1:]]))
