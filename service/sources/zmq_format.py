"""The ZeroMQ wire format of frame batches (docs/zmq-frames.md): a JSON header part, then the raw pixels.

One message carries frames with consecutive indices; a gap between messages is a gap in the stream.
The pixel part is the C-ordered (N, H, W) array in little-endian words, sent and received without
copies above ZeroMQ's copy threshold. A header alone with ``"end": true`` ends the stream.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from service.sources.base import FrameBatch, StreamFormat

FORMAT = "meniscope.frames"
VERSION = 1
#: Timestamps within this many seconds of ``t0 + k / fps`` are sent as ``t0`` alone.
REGULAR_TOLERANCE_S = 1e-9
_DTYPES = {"uint8": np.dtype("<u1"), "uint16": np.dtype("<u2")}

Buffer = bytes | memoryview


@dataclass(frozen=True)
class Message:
    """One decoded message: its sequence number, the frames (None when the stream ends) and their format."""

    sequence: int
    batch: FrameBatch | None
    format: StreamFormat | None


def encode(batch: FrameBatch, fmt: StreamFormat, sequence: int) -> list[Buffer]:
    """The parts [header, pixels] of a batch whose indices are consecutive; the pixels part is not copied."""
    n, height, width = batch.pixels.shape
    if n == 0 or np.any(np.diff(batch.indices) != 1):
        raise ValueError("a message holds one or more frames with consecutive indices")
    header: dict[str, object] = {
        "format": FORMAT,
        "version": VERSION,
        "sequence": sequence,
        "dtype": batch.pixels.dtype.name,
        "shape": [n, height, width],
        "bit_depth": fmt.bit_depth,
        "fps": fmt.fps,
        "index": int(batch.indices[0]),
    }
    t0 = float(batch.timestamps[0])
    regular = t0 + np.arange(n) / fmt.fps
    if np.all(np.abs(batch.timestamps - regular) <= REGULAR_TOLERANCE_S):
        header["t0"] = t0
    else:
        header["timestamps"] = batch.timestamps.tolist()
    pixels = np.ascontiguousarray(batch.pixels, dtype=_DTYPES[batch.pixels.dtype.name])
    return [json.dumps(header, allow_nan=False).encode(), memoryview(pixels).cast("B")]


def encode_end(sequence: int) -> list[Buffer]:
    """The one-part message that ends a stream."""
    return [json.dumps({"format": FORMAT, "version": VERSION, "sequence": sequence, "end": True}).encode()]


def decode(parts: Sequence[Buffer]) -> Message:
    """A message from its parts; the pixels are a read-only view of the received buffer (no copy).

    Raises ValueError naming what is wrong with a message that does not follow the format.
    """
    try:
        header = json.loads(bytes(parts[0]))
    except (IndexError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"the header part is not JSON ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise ValueError(f"not a {FORMAT} message (header {str(header)[:80]})")
    if header.get("version") != VERSION:
        raise ValueError(f"the sender speaks {FORMAT} version {header.get('version')}, this receiver version {VERSION}")
    sequence = _int(header, "sequence")
    if header.get("end") is True:
        return Message(sequence, None, None)
    if len(parts) != 2:
        raise ValueError(f"a frame message has 2 parts (header, pixels), got {len(parts)}")
    dtype = _DTYPES.get(str(header.get("dtype")))
    shape = header.get("shape")
    if dtype is None:
        raise ValueError(f"dtype {header.get('dtype')!r} is not one of {', '.join(_DTYPES)}")
    if not (isinstance(shape, list) and len(shape) == 3 and all(isinstance(s, int) and s > 0 for s in shape)):
        raise ValueError(f"shape {shape!r} is not [frames, height, width] of positive integers")
    n, height, width = shape
    fps, bit_depth, index = _number(header, "fps"), _int(header, "bit_depth"), _int(header, "index")
    if not (fps > 0 and 1 <= bit_depth <= 8 * dtype.itemsize):
        raise ValueError(f"fps {fps} or bit depth {bit_depth} out of range for {dtype.name}")
    pixels = np.frombuffer(parts[1], dtype=dtype)
    if pixels.size != n * height * width:
        raise ValueError(f"the pixel part holds {pixels.nbytes} bytes, the header announces {shape} {dtype.name}")
    if "timestamps" in header:
        timestamps = np.asarray(header["timestamps"], dtype=np.float64)
        if timestamps.shape != (n,) or not np.isfinite(timestamps).all():
            raise ValueError(f"timestamps must be {n} finite numbers")
    else:
        timestamps = _number(header, "t0") + np.arange(n) / fps
    batch = FrameBatch(
        pixels.reshape(n, height, width).astype(dtype.newbyteorder("="), copy=False),
        np.arange(index, index + n, dtype=np.int64),
        timestamps,
    )
    return Message(sequence, batch, StreamFormat(width, height, batch.pixels.dtype, bit_depth, fps))


def _int(header: dict, key: str) -> int:
    value = header.get(key)
    if not isinstance(value, int) or isinstance(value, bool):
        raise ValueError(f"header field {key!r} must be an integer, got {value!r}")
    return value


def _number(header: dict, key: str) -> float:
    value = header.get(key)
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise ValueError(f"header field {key!r} must be a finite number, got {value!r}")
    return float(value)
