"""Recordings: high-speed video files (.cine, .avi) read and written as pixel words exactly as stored.

``open_recording`` and ``open_writer`` pick the format by file extension; every problem with a file
(missing, empty, truncated, corrupt, unsupported) is one :class:`~service.errors.MeniscopeError` line.
"""
from __future__ import annotations

from pathlib import Path
from typing import TypeVar

from service.errors import MeniscopeError
from service.recordings.avi import AviRecording, AviWriter
from service.recordings.base import Recording, RecordingWriter
from service.recordings.cine import CineRecording
from service.recordings.cine_writer import CineWriter

__all__ = ["Recording", "RecordingWriter", "open_recording", "open_writer"]

_READERS: dict[str, type[Recording]] = {".cine": CineRecording, ".avi": AviRecording}
_WRITERS: dict[str, type[RecordingWriter]] = {".cine": CineWriter, ".avi": AviWriter}
_T = TypeVar("_T")


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


def open_writer(path: str | Path, width: int, height: int, fps: float, bit_depth: int = 8,
                trigger_frame: int = 0) -> RecordingWriter:
    """A new recording of ``width`` x ``height`` px at ``fps`` frames/s, the format chosen by extension.

    ``bit_depth`` 8 stores uint8 words, 12 and 16 uint16 words (.cine only); ``trigger_frame`` is the
    index of the frame at time 0 (.cine only).
    """
    path = Path(path)
    return _by_extension(path, _WRITERS)(path, width, height, fps, bit_depth, trigger_frame)


def _by_extension(path: Path, table: dict[str, _T]) -> _T:
    """The entry of ``table`` for the file's extension, or an error listing the supported ones."""
    try:
        return table[path.suffix.lower()]
    except KeyError:
        raise MeniscopeError(
            path, f"unsupported recording type {path.suffix or '(no extension)'!r}: use {' or '.join(table)}"
        ) from None
