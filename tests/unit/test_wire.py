"""The frame codec: round trips without copies, and every malformed kind rejected."""

from __future__ import annotations

import json

import numpy as np
import pytest

from semservo.messages import FRAME_TOPIC, FrameHeader
from semservo.wire import WireError, decode_frame, encode_frame, frame_header

METADATA = dict(pixel_size_nm=176.9, magnification=1200.0, dwell_ns=720.0, source="test")
LIMIT = 2**20


def parts_for(pixels: np.ndarray, **changes) -> list:
    header = frame_header(pixels, seq=7, acquired_at_ns=123, **METADATA)
    topic, header_bytes, data = encode_frame(header, pixels)
    fields = json.loads(header_bytes)
    fields.update(changes)
    return [topic, json.dumps(fields).encode(), data]


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_round_trip_keeps_header_and_pixels(dtype):
    pixels = (np.arange(48 * 64).reshape(48, 64) % 251).astype(dtype)
    frame = decode_frame(parts_for(pixels), max_bytes=LIMIT)
    assert frame.header.seq == 7
    assert frame.header.shape == (48, 64)
    assert frame.header.dtype == np.dtype(dtype).name
    assert frame.header.magnification == 1200.0
    assert frame.header.published_at_ns >= frame.header.acquired_at_ns
    np.testing.assert_array_equal(frame.pixels, pixels)


def test_encode_hands_over_the_array_itself_and_decode_wraps_the_buffer():
    pixels = np.zeros((32, 32), np.uint16)
    header = frame_header(pixels, seq=0, acquired_at_ns=0, **METADATA)
    assert encode_frame(header, pixels)[2] is pixels  # no copy on send
    buffer = bytearray(pixels.tobytes())
    frame = decode_frame([FRAME_TOPIC, header.model_dump_json().encode(), buffer], max_bytes=LIMIT)
    assert np.shares_memory(frame.pixels, np.frombuffer(buffer, np.uint16))  # no copy on receive


def test_big_endian_pixels_are_sent_little_endian():
    pixels = np.arange(16, dtype=">u2").reshape(4, 4)
    header = frame_header(pixels, seq=0, acquired_at_ns=0, **METADATA)
    frame = decode_frame(encode_frame(header, pixels), max_bytes=LIMIT)
    np.testing.assert_array_equal(frame.pixels, pixels)


@pytest.mark.parametrize(
    "mutate, reason",
    [
        (lambda parts: parts[:2], "parts"),
        (lambda parts: parts + [b"extra"], "parts"),
        (lambda parts: [b"other"] + parts[1:], "parts"),
        (lambda parts: [parts[0], b"{not json", parts[2]], "header"),
        (lambda parts: [parts[0], b"[1, 2]", parts[2]], "header"),
        (lambda parts: [parts[0], parts[1], parts[2][:-1]], "size"),
        (lambda parts: [parts[0], parts[1], parts[2].tobytes() + b"\0"], "size"),
        (lambda parts: [parts[0], parts[1], b""], "size"),
    ],
    ids=["two-parts", "four-parts", "wrong-topic", "not-json", "not-object", "truncated", "too-long", "empty"],
)
def test_malformed_structure_is_rejected_with_its_reason(mutate, reason):
    pixels = np.ones((16, 16), np.uint8)
    with pytest.raises(WireError) as caught:
        decode_frame(mutate(parts_for(pixels)), max_bytes=LIMIT)
    assert caught.value.reason == reason


@pytest.mark.parametrize(
    "changes, reason",
    [
        ({"v": 2}, "version"),
        ({"v": None}, "version"),
        ({"dtype": "int64"}, "dtype"),
        ({"shape": [16, -16]}, "header"),
        ({"seq": "seven"}, "header"),
        ({"pixel_size_nm": 0}, "header"),
        ({"unexpected": 1}, "header"),
        ({"shape": [8, 8]}, "size"),
    ],
    ids=["version-2", "no-version", "int64", "negative-shape", "bad-seq", "zero-pixel-size", "extra-field", "shape-mismatch"],
)
def test_malformed_header_is_rejected_with_its_reason(changes, reason):
    pixels = np.ones((16, 16), np.uint8)
    with pytest.raises(WireError) as caught:
        decode_frame(parts_for(pixels, **changes), max_bytes=LIMIT)
    assert caught.value.reason == reason


def test_missing_header_field_is_named():
    pixels = np.ones((16, 16), np.uint8)
    parts = parts_for(pixels)
    fields = json.loads(parts[1])
    del fields["acquired_at_ns"]
    with pytest.raises(WireError, match="acquired_at_ns"):
        decode_frame([parts[0], json.dumps(fields).encode(), parts[2]], max_bytes=LIMIT)


def test_acquisition_fields_a_source_does_not_know_stay_unknown():
    pixels = np.ones((16, 16), np.uint8)
    parts = parts_for(pixels)
    fields = json.loads(parts[1])
    for name in ("magnification", "pixel_size_nm", "dwell_ns"):
        del fields[name]
    header = decode_frame([parts[0], json.dumps(fields).encode(), parts[2]], max_bytes=LIMIT).header
    assert (header.magnification, header.pixel_size_nm, header.dwell_ns, header.working_distance_mm) == (None,) * 4
    fields["pixel_size_nm"] = -1.0  # known, but wrong: still refused
    with pytest.raises(WireError, match="pixel_size_nm"):
        decode_frame([parts[0], json.dumps(fields).encode(), parts[2]], max_bytes=LIMIT)


def test_oversized_message_is_rejected():
    pixels = np.ones((256, 256), np.uint16)
    with pytest.raises(WireError) as caught:
        decode_frame(parts_for(pixels), max_bytes=100_000)
    assert caught.value.reason == "oversized"


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nonfinite_float_frame_is_rejected(bad):
    pixels = np.ones((16, 16), np.float32)
    pixels[3, 4] = bad
    with pytest.raises(WireError) as caught:
        decode_frame(parts_for(pixels), max_bytes=LIMIT)
    assert caught.value.reason == "nonfinite"


def test_frame_header_refuses_unsupported_arrays():
    with pytest.raises(ValueError, match="int64"):
        frame_header(np.zeros((4, 4), np.int64), seq=0, acquired_at_ns=0, **METADATA)
    with pytest.raises(ValueError, match="2-D"):
        frame_header(np.zeros((4, 4, 3), np.uint8), seq=0, acquired_at_ns=0, **METADATA)


def test_header_bytes_counts_pixels():
    header = FrameHeader(seq=0, acquired_at_ns=0, published_at_ns=0, shape=(1024, 1536), dtype="uint16", **METADATA)
    assert header.nbytes == 1024 * 1536 * 2


def test_the_frame_header_carries_every_acquisition_field():
    from semservo.messages import ACQUISITION_FIELDS, FrameHeader

    assert set(ACQUISITION_FIELDS) <= set(FrameHeader.model_fields)
