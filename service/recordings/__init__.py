"""Recordings: high-speed video files (.cine, .avi) read and written as pixel words exactly as stored.

``open_recording`` and ``open_writer`` pick the format by file extension; every problem with a file
(missing, empty, truncated, corrupt, unsupported) is one :class:`~service.errors.MeniscopeError` line.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from service.errors import MeniscopeError
from service.recordings.base import Recording, RecordingWriter

__all__ = ["Recording", "RecordingWriter", "open_recording", "open_writer"]

#: Reader and writer classes by extension, as (module, class): a format's module (OpenCV for .avi) loads when a file
#: of it is opened, so that ``meniscope info REC.cine`` starts fast.
_READERS = {".cine": ("service.recordings.cine", "CineRecording"), ".avi": ("service.recordings.avi", "AviRecording")}
_WRITERS = {".cine": ("service.recordings.cine_writer", "CineWriter"), ".avi": ("service.recordings.avi", "AviWriter")}


def open_recording(path: str | Path) -> Recording:
    """Open a recording for reading, the reader chosen by extension (each reader checks the magic bytes)."""
    path = Path(path)
    if not path.exists():
        raise MeniscopeError(path, "no such file")
    if path.is_dir():
        raise MeniscopeError(path, "is a folder, not a recording")
    reader = _by_extension(path, _READERS)
    if path.stat().st_size == 0:
        raise MeniscopeError(path, "the file is empty")
    return reader(path)


def open_writer(
    path: str | Path, width: int, height: int, fps: float, bit_depth: int = 8, trigger_frame: int = 0
) -> RecordingWriter:
    """A new recording of ``width`` x ``height`` px at ``fps`` frames/s, the format chosen by extension.

    ``bit_depth`` 8 stores uint8 words, 12 and 16 uint16 words (.cine only); ``trigger_frame`` is the
    index of the frame at time 0 (.cine only).
    """
    path = Path(path)
    return _by_extension(path, _WRITERS)(path, width, height, fps, bit_depth, trigger_frame)


def _by_extension(path: Path, table: dict[str, tuple[str, str]]) -> type:
    """The class of ``table`` for the file's extension (its module imported now), or an error listing the supported
    ones."""
    try:
        module, name = table[path.suffix.lower()]
    except KeyError:
        raise MeniscopeError(
            path, f"unsupported recording type {path.suffix or '(no extension)'!r}: use {' or '.join(table)}"
        ) from None
    return getattr(importlib.import_module(module), name)
