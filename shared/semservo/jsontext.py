"""Strict JSON for results files: what a benchmark or a reproduction writes must load in
any JSON reader (a browser, ``jq``, pandas), not only in Python's.

Python's ``json`` writes a float that is not finite as the bare tokens ``NaN`` and
``Infinity``, which are not JSON; and it cannot write numpy's scalars and arrays at all.
:func:`dumps` writes a not-finite number as ``null`` (a refused estimate has no value,
and ``null`` says so) and numpy's values as the plain numbers and lists they hold.
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np


def plain(value: Any) -> Any:
    """``value`` with numpy's scalars and arrays made Python numbers and lists, tuples
    made lists, dataclasses made dicts, paths made strings, and every float that is not
    finite made ``None``."""
    if isinstance(value, dict):
        return {str(key) if not isinstance(key, (str, int, float, bool)) and key is not None else key: plain(item)
                for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(item) for item in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        return plain(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return plain(dataclasses.asdict(value))
    if isinstance(value, Path):
        return str(value)
    return value


def dumps(value: Any, **options: Any) -> str:
    """``value`` as strict JSON text (:func:`plain`; ``json.dumps``'s ``options``, such as
    ``indent``). Raises ``TypeError`` for what has no JSON form, as ``json.dumps`` does."""
    return json.dumps(plain(value), allow_nan=False, **options)
