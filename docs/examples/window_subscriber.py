"""Subscribe to `meniscope serve`'s window results over ZeroMQ, as a printer's controller would.

    python docs/examples/window_subscriber.py [--endpoint tcp://127.0.0.1:5556] [--count N]

Prints one line per window: its id, frames, status, dominant frequency and decay rate, settling time.
Needs only pyzmq. Message format: docs/service.md, "ZeroMQ".
"""
import argparse
import json

import zmq

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--endpoint", default="tcp://127.0.0.1:5556", help="the service's zmq_publish endpoint")
parser.add_argument("--count", type=int, default=0, help="stop after this many windows (0: never)")
args = parser.parse_args()

socket = zmq.Context.instance().socket(zmq.SUB)
socket.connect(args.endpoint)
socket.setsockopt(zmq.SUBSCRIBE, b"meniscope.window")  # the topic: the first part of every message
received = 0
while args.count == 0 or received < args.count:
    topic, body = socket.recv_multipart()
    message = json.loads(body)  # {"schema": "meniscope.window/1", "type": "window", "id", "stored", "source", "fps", "window"}
    w = message["window"]
    mode = w["modes"][0] if w["modes"] else None
    print(f"window {message['id']}: frames {w['start_frame']}-{w['end_frame']} {w['status']}"
          + (f", {mode['frequency_hz']:.0f} Hz, decay {mode['decay_rate_per_s']:.0f} /s" if mode else "")
          + (f", settled after {w['settling_time_s'] * 1e3:.2f} ms" if w["settled"] else ", not settled"), flush=True)
    received += 1
