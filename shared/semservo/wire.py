"""Frames on the wire: ``[topic, header JSON, raw pixels]`` with no copies of the pixels.

Sending hands the numpy buffer itself to ZeroMQ (``copy=False``); receiving wraps the
ZeroMQ message memory in a read-only array (``numpy.frombuffer``). :func:`decode_frame`
is the one place a receiver checks what arrived; anything wrong raises
:class:`WireError` whose ``reason`` is the counter name the receiver increments.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import pydantic
import pydantic_core

from semservo.messages import FRAME_TOPIC, PIXEL_DTYPES, WIRE_VERSION, FrameHeader

#: Reasons a received message is dropped; each is a counter ``dropped_<reason>``.
DROP_REASONS = ("parts", "oversized", "header", "version", "size", "dtype", "nonfinite")


class WireError(ValueError):
    """A received message that is not a valid frame. ``reason`` is one of DROP_REASONS."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True)
class Frame:
    """A frame as received: its header and a read-only view of the pixels."""

    header: FrameHeader
    pixels: np.ndarray


def frame_header(pixels: np.ndarray, *, seq: int, acquired_at_ns: int, **metadata) -> FrameHeader:
    """Header for ``pixels``, stamped as published now."""
    dtype = pixels.dtype.name  # the name ignores byte order; encode_frame fixes that
    if dtype not in PIXEL_DTYPES:
        raise ValueError(f"frames carry {', '.join(PIXEL_DTYPES)} pixels, not {pixels.dtype}")
    if pixels.ndim != 2:
        raise ValueError(f"a frame is a 2-D image, got shape {pixels.shape}")
    return FrameHeader(
        seq=seq,
        acquired_at_ns=acquired_at_ns,
        published_at_ns=time.time_ns(),
        shape=pixels.shape,
        dtype=dtype,
        **metadata,
    )


def encode_frame(header: FrameHeader, pixels: np.ndarray) -> list:
    """The three parts to send. The pixel part is the array's own buffer (no copy)."""
    wire_dtype = PIXEL_DTYPES[header.dtype]
    if pixels.dtype != wire_dtype or not pixels.flags.c_contiguous:
        pixels = np.ascontiguousarray(pixels, dtype=wire_dtype)  # only byte order or layout
    if pixels.shape != header.shape:
        raise ValueError(f"header says {header.shape}, pixels are {pixels.shape}")
    return [FRAME_TOPIC, header.model_dump_json().encode(), pixels]


def _buffer(part) -> memoryview:
    # zmq.Frame (copy=False) exposes .buffer; bytes and memoryviews are used as they are.
    return part.buffer if hasattr(part, "buffer") else memoryview(part)


def decode_frame(parts: Sequence, *, max_bytes: int) -> Frame:
    """Check a received multipart message and return the frame it carries.

    Checks, in order: three parts, total size within ``max_bytes``, a JSON header of the
    known wire version and schema, a pixel part of exactly ``rows * cols * itemsize``
    bytes, and finite values for float frames. The first failure raises
    :class:`WireError`.
    """
    if len(parts) != 3:
        raise WireError("parts", f"expected 3 parts [topic, header, pixels], got {len(parts)}")
    topic, header_part, pixel_part = (_buffer(part) for part in parts)
    total = topic.nbytes + header_part.nbytes + pixel_part.nbytes
    if total > max_bytes:
        raise WireError("oversized", f"{total} bytes exceeds the limit of {max_bytes}")
    if bytes(topic) != FRAME_TOPIC:
        raise WireError("parts", f"unknown topic {bytes(topic)[:32]!r}")
    try:
        fields = pydantic_core.from_json(bytes(header_part))
    except ValueError as error:
        raise WireError("header", f"header is not JSON: {error}") from None
    if not isinstance(fields, dict):
        raise WireError("header", "header is not a JSON object")
    if fields.get("v") != WIRE_VERSION:
        raise WireError("version", f"wire version {fields.get('v')!r}, this build speaks {WIRE_VERSION}")
    if fields.get("dtype") not in PIXEL_DTYPES:
        raise WireError("dtype", f"pixel type {fields.get('dtype')!r} is not one of {sorted(PIXEL_DTYPES)}")
    try:
        header = FrameHeader.model_validate(fields)
    except pydantic.ValidationError as error:
        first = error.errors()[0]
        where = ".".join(str(item) for item in first["loc"]) or "header"
        raise WireError("header", f"{where}: {first['msg']}") from None
    if pixel_part.nbytes != header.nbytes:
        kind = "truncated" if pixel_part.nbytes < header.nbytes else "too long"
        raise WireError(
            "size",
            f"pixel part {kind}: {pixel_part.nbytes} bytes for {header.shape} {header.dtype} "
            f"({header.nbytes} expected)",
        )
    pixels = np.frombuffer(pixel_part, dtype=PIXEL_DTYPES[header.dtype]).reshape(header.shape)
    if pixels.dtype.kind == "f" and not np.isfinite(pixels).all():
        raise WireError("nonfinite", "float frame contains NaN or infinity")
    return Frame(header=header, pixels=pixels)
