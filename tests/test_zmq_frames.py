"""Frames over ZeroMQ (docs/zmq-frames.md): the wire format, its zero-copy path, PUB's drop-don't-block, the sender verb."""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zmq

from service.cli import main
from service.errors import MeniscopeError
from service.recordings import open_writer
from service.sources import FrameBatch, FrameSender, StreamFormat, open_source, zmq_format
from tests.servicekit import free_port

FMT16 = StreamFormat(width=5, height=3, dtype=np.dtype(np.uint16), bit_depth=12, fps=19000.0)
BIG = StreamFormat(width=512, height=512, dtype=np.dtype(np.uint16), bit_depth=12, fps=19000.0)  # 512 KiB a frame


def batch(fmt: StreamFormat, n: int, first: int = 0, times: np.ndarray | None = None) -> FrameBatch:
    pixels = (np.arange(n * fmt.height * fmt.width) % 2**fmt.bit_depth).astype(fmt.dtype)
    indices = np.arange(first, first + n, dtype=np.int64)
    return FrameBatch(pixels.reshape(n, fmt.height, fmt.width), indices, indices / fmt.fps if times is None else times)


def header(parts: list) -> dict:
    return json.loads(bytes(parts[0]))


class TestWireFormat:
    def test_regular_times_travel_as_t0_and_come_back_to_the_nanosecond(self) -> None:
        sent = batch(FMT16, 4, first=7)
        parts = zmq_format.encode(sent, FMT16, sequence=3)
        assert header(parts) == {
            "format": "meniscope.frames",
            "version": 1,
            "sequence": 3,
            "dtype": "uint16",
            "shape": [4, 3, 5],
            "bit_depth": 12,
            "fps": 19000.0,
            "index": 7,
            "t0": 7 / 19000.0,
        }
        got = zmq_format.decode(parts)
        assert (got.sequence, got.format) == (3, FMT16)
        np.testing.assert_array_equal(got.batch.pixels, sent.pixels)
        np.testing.assert_array_equal(got.batch.indices, sent.indices)
        np.testing.assert_allclose(got.batch.timestamps, sent.timestamps, rtol=0, atol=1e-9)

    def test_irregular_times_travel_as_a_list_exactly(self) -> None:
        times = np.array([0.1, 0.2000003, 0.35])
        fmt8 = StreamFormat(5, 3, np.dtype(np.uint8), 8, 10.0)
        parts = zmq_format.encode(batch(fmt8, 3, times=times), fmt8, sequence=0)
        assert header(parts)["timestamps"] == times.tolist() and "t0" not in header(parts)
        got = zmq_format.decode(parts).batch
        assert got.pixels.dtype == np.uint8
        np.testing.assert_array_equal(got.timestamps, times)

    def test_the_end_message_carries_no_frames(self) -> None:
        got = zmq_format.decode(zmq_format.encode_end(sequence=9))
        assert (got.sequence, got.batch, got.format) == (9, None, None)

    def test_a_message_holds_consecutive_frames_only(self) -> None:
        gappy = batch(FMT16, 3).select(np.array([0, 2]))
        with pytest.raises(ValueError, match="consecutive"):
            zmq_format.encode(gappy, FMT16, 0)

    def test_pixels_are_neither_copied_to_send_nor_on_receipt(self) -> None:
        sent = batch(FMT16, 4)
        parts = zmq_format.encode(sent, FMT16, 0)
        assert np.shares_memory(np.frombuffer(parts[1], np.uint8), sent.pixels)
        received = bytearray(parts[1])  # the receiving socket's buffer
        got = zmq_format.decode([parts[0], memoryview(received)]).batch
        assert np.shares_memory(got.pixels, np.frombuffer(received, np.uint8))

    @pytest.mark.parametrize(
        ("change", "problem"),
        [
            (lambda h, p: [b"{not json", p], "not JSON"),
            (lambda h, p: [json.dumps({**h, "format": "other"}).encode(), p], "not a meniscope.frames message"),
            (lambda h, p: [json.dumps({**h, "version": 2}).encode(), p], "version 2"),
            (lambda h, p: [json.dumps({**h, "dtype": "float32"}).encode(), p], "dtype 'float32'"),
            (lambda h, p: [json.dumps({**h, "shape": [4, 3]}).encode(), p], "shape"),
            (lambda h, p: [json.dumps(h).encode(), p[:-2]], "holds 118 bytes"),
            (lambda h, p: [json.dumps(h).encode()], "2 parts"),
            (lambda h, p: [json.dumps({**h, "fps": -1}).encode(), p], "fps -1"),
            (lambda h, p: [json.dumps({**h, "index": "7"}).encode(), p], "'index' must be an integer"),
            (lambda h, p: [json.dumps({**h, "timestamps": [0.1]}).encode(), p], "timestamps must be 4"),
        ],
    )
    def test_a_malformed_message_is_refused_with_the_reason(self, change, problem: str) -> None:
        parts = zmq_format.encode(batch(FMT16, 4), FMT16, 0)
        with pytest.raises(ValueError, match=problem):
            zmq_format.decode(change(header(parts), bytes(parts[1])))


@pytest.fixture
def sender() -> Iterator[FrameSender]:
    with FrameSender("tcp://127.0.0.1:*", BIG) as sender:
        yield sender


def publish(sender: FrameSender, batches: list[FrameBatch], end: bool = True) -> threading.Thread:
    """A thread that waits for a subscriber, then sends ``batches`` and (``end``) ends the stream."""

    def run() -> None:
        if sender.wait_for_subscriber(10.0):
            for b in batches:
                sender.send(b)
            if end:
                sender.close()

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def uri(sender: FrameSender) -> str:
    return sender.endpoint.replace("tcp://", "zmq+tcp://")


class TestOverLoopback:
    def test_received_pixels_are_a_view_of_zeromqs_message(self, sender: FrameSender) -> None:
        publish(sender, [batch(BIG, 2)])
        with open_source(uri(sender)) as source:
            got = source.read(2)
        base = got.pixels
        while isinstance(base, np.ndarray):
            base = base.base
        assert isinstance(base, memoryview) and isinstance(base.obj, zmq.Frame)

    def test_a_receiver_that_does_not_read_never_blocks_the_sender(self, sender: FrameSender) -> None:
        sent = [batch(BIG, 2, first=2 * k) for k in range(300)]  # 300 messages of 1 MiB
        thread = publish(sender, sent, end=False)
        with open_source(uri(sender), timeout=0.2) as source:  # subscribed; now it stops reading
            thread.join(60)
            assert not thread.is_alive(), "the sender blocked on a subscriber that does not read"
            assert sender.sequence == 300
            while (got := source.read(64)) is not None and len(got):
                pass  # take what was queued while it was not reading
            sender.send(batch(BIG, 2, first=600))  # the stream goes on: its next frames reveal what was lost
            for _ in range(300):  # ~60 s at the 0.2 s read timeout: a guard, not a time being measured
                got = source.read(64)
                if got is not None and len(got) and got.indices[-1] == 601:
                    break
            else:
                pytest.fail("the frames sent after the flood never arrived")
            stats = source.stats
            assert stats.frames < 602 and stats.gaps >= 1
            assert stats.frames + stats.dropped <= 602
            assert source.describe()["lost_messages"] >= stats.gaps

    def test_a_sender_that_starts_again_ends_the_stream(self, sender: FrameSender) -> None:
        publish(sender, [batch(BIG, 2, first=100), batch(BIG, 2, first=0)])
        with open_source(uri(sender)) as source:
            assert source.read(2).indices.tolist() == [100, 101]
            assert source.read(2) is None

    def test_a_change_of_frame_size_mid_stream_is_an_error(self, sender: FrameSender) -> None:
        small = StreamFormat(8, 8, BIG.dtype, BIG.bit_depth, BIG.fps)

        def run() -> None:
            if sender.wait_for_subscriber(10.0):
                sender.send(batch(BIG, 1))
                sender.send(batch(small, 1, first=1))

        threading.Thread(target=run, daemon=True).start()
        with open_source(uri(sender), timeout=5.0) as source:
            with pytest.raises(MeniscopeError, match="changed the frame format"):
                source.read(2)


class TestPublishFramesVerb:
    def test_replays_a_recording_to_a_subscriber_and_ends_the_stream(self, tmp_path: Path) -> None:
        rec = tmp_path / "rec.cine"
        with open_writer(rec, 32, 32, 19000.0, bit_depth=12) as writer:
            writer.write(np.full((500, 32, 32), 4095, np.uint16))
        endpoint = f"tcp://127.0.0.1:{free_port()}"
        result: list[int] = []
        verb = threading.Thread(
            target=lambda: result.append(main(["publish-frames", str(rec), "--bind", endpoint, "--speed", "0.5"])),
            daemon=True,
        )
        verb.start()
        with open_source(endpoint.replace("tcp://", "zmq+tcp://")) as source:
            batches = []
            while (got := source.read(128)) is not None:
                batches.append(got)
        verb.join(10)
        frames = FrameBatch.concatenate(batches)
        assert result == [0]
        assert (source.stats.frames, frames.indices[-1]) == (500, 499)  # paced: a reader keeps up, nothing lost
        assert (frames.pixels == 4095).all()

    def test_a_missing_recording_is_a_one_line_error(self, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
        assert main(["publish-frames", str(tmp_path / "none.cine")]) == 2
        err = capsys.readouterr().err
        assert "none.cine: no such file" in err and err.count("\n") == 1

    def test_a_bad_speed_is_a_one_line_error(self, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
        rec = tmp_path / "rec.cine"
        with open_writer(rec, 8, 8, 100.0) as writer:
            writer.write(np.zeros((2, 8, 8), np.uint8))
        assert main(["publish-frames", str(rec), "--speed", "fast"]) == 2
        assert "bad option speed='fast'" in capsys.readouterr().err
