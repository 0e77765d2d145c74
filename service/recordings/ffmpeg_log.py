"""The decode errors FFmpeg reports while OpenCV reads a video, which OpenCV itself drops.

FFmpeg conceals damaged frames (a "slice CRC mismatch" in FFV1, a broken JPEG in MJPG) and returns them
as if good; OpenCV's ``read()`` then says ``ok``. FFmpeg does write a line to the process's standard error
(file descriptor 2, below Python) for each, such as ``[ffv1 @ 0x...] slice CRC mismatch``. While frames
are decoded, :func:`decoder_errors` sends descriptor 2 to a temporary file, writes everything caught on to
the real standard error unchanged afterwards, and hands back the decoders' error lines. One capture at a
time (a lock): descriptor 2 belongs to the whole process.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: An FFmpeg log line from a decoder (not the container's demuxer, whose complaints OpenCV survives).
DECODER_LINE = re.compile(r"^\[(?!avi\b|NULL\b)\w+ @ 0x[0-9a-f]+\] (.+)$")
_LOCK = threading.Lock()


@contextmanager
def decoder_errors() -> Iterator[list[str]]:
    """The decoder error lines FFmpeg writes while the block runs (filled in when it ends)."""
    found: list[str] = []
    with _LOCK, tempfile.TemporaryFile() as caught:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(caught.fileno(), 2)
        try:
            yield found
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            caught.seek(0)
            text = caught.read()
            if text:
                os.write(2, text)
            found.extend(
                m.group(0)
                for line in text.decode(errors="replace").splitlines()
                if (m := DECODER_LINE.match(line.strip()))
            )
