"""Small helpers for the words the services, the CLI and the reports say to people."""

from __future__ import annotations


def counted(number: int, noun: str, plural: str | None = None) -> str:
    """``number`` and ``noun``, plural unless one: ``counted(1, "wide sweep")`` is
    "1 wide sweep", ``counted(3, "wide sweep")`` "3 wide sweeps"."""
    return f"{number} {noun if number == 1 else plural or noun + 's'}"
