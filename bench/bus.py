"""Per-hop latency and throughput of the bus: a publisher process and a subscriber process.

    python -m bench.bus --json

Latency: messages are sent at a spaced rate, each stamped at send; the receiver takes `recv − send` after
decoding (both read the host's CLOCK_MONOTONIC). Throughput: a lossless burst, messages per second received.
Measured for a `gesture.step`-sized message and a 512² rgb24 `render.frame`, over ipc and tcp on loopback.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import tempfile
import time

import numpy as np
import zmq

from agent.latency import percentiles
from bench.machine import machine_report
from ecas.core.bus import Publisher, Subscriber
from ecas.core.messages import Command, Control, GestureStep, RenderFrame
from ecas.core.threads import limit_threads
from ecas.core.timing import NS_PER_MS

FRAME_SIDE = 512


def gesture_message() -> GestureStep:
    rng = np.random.default_rng(0)
    return GestureStep(
        poses=rng.standard_normal((2, 55, 3), np.float32),
        trans=np.zeros((2, 3), np.float32),
        expressions=rng.standard_normal((2, 100), np.float32),
        tokens=np.arange(20, dtype=np.int32),
    )


def frame_message() -> RenderFrame:
    image = np.random.default_rng(0).integers(0, 255, (FRAME_SIDE, FRAME_SIDE, 3), np.uint8)
    return RenderFrame(width=FRAME_SIDE, height=FRAME_SIDE, image=image)


MESSAGES = {"gesture.step": gesture_message, "render.frame_512": frame_message}


def publish(address: str, kind: str, count: int, spacing_s: float, joined, finished) -> None:
    limit_threads()
    pub = Publisher(zmq.Context.instance(), address, "bench", lossless=True)
    while not joined.is_set():
        pub.send(Control(command=Command.HEARTBEAT))
        time.sleep(0.01)
    msg = MESSAGES[kind]()
    next_send = time.monotonic()
    for _ in range(count):
        if spacing_s:
            while time.monotonic() < next_send:
                pass
            next_send += spacing_s
        msg.t_ns = time.monotonic_ns()
        pub.send(msg)
    pub.send(Control(command=Command.EOS))
    finished.wait(120)  # closing earlier would discard what is still queued
    pub.close()


def measure(address: str, kind: str, count: int, spacing_s: float) -> dict:
    ctx = zmq.Context.instance()
    sub = Subscriber(ctx, [address], ["control", kind.split("_")[0]], live_queue=None)
    spawn = mp.get_context("spawn")
    joined, finished = spawn.Event(), spawn.Event()
    proc = spawn.Process(target=publish, args=(address, kind, count, spacing_s, joined, finished))
    proc.start()
    latencies_ms, first_sent_ns, last_ns, done = [], None, None, False
    while not done:
        if not sub.socket.poll(10_000):
            raise TimeoutError(f"no message from the publisher on {address}")
        sub.poll_into_queue()
        now = time.monotonic_ns()
        if sub.controls and not joined.is_set():
            joined.set()
        done = any(c.command == Command.EOS for c in sub.controls)
        sub.controls.clear()
        while sub.queue:
            msg = sub.queue.popleft()
            latencies_ms.append((now - msg.t_ns) / NS_PER_MS)
            first_sent_ns = first_sent_ns or msg.t_ns
            last_ns = now
    finished.set()
    proc.join()
    sub.close()
    rate = len(latencies_ms) / ((last_ns - first_sent_ns) / 1e9) if latencies_ms else 0.0
    return {"latency_ms": percentiles(latencies_ms), "received": len(latencies_ms), "msgs_per_s": round(rate, 1)}


def run(count: int) -> dict:
    results = {}
    with tempfile.TemporaryDirectory(prefix="bench-bus-") as tmp:
        addresses = {"ipc": lambda i: f"ipc://{tmp}/bench{i}.sock", "tcp": lambda i: f"tcp://127.0.0.1:{5790 + i}"}
        for transport, address in addresses.items():
            for i, (kind, n, spacing_s) in enumerate(
                (("gesture.step", count, 0.002), ("render.frame_512", count // 4, 0.01))
            ):
                latency = measure(address(2 * i), kind, n, spacing_s)
                burst = measure(address(2 * i + 1), kind, n, 0.0)
                results[f"{kind}/{transport}"] = {
                    "latency_ms": latency["latency_ms"],
                    "burst_msgs_per_s": burst["msgs_per_s"],
                    "received": latency["received"],
                }
    return results


def main(argv=None) -> None:
    p = argparse.ArgumentParser(
        prog="ecas bench bus", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--count", type=int, default=2000, help="messages per measurement")
    p.add_argument("--json", action="store_true", help="print JSON only")
    args = p.parse_args(argv)
    results = run(args.count)
    if args.json:
        print(json.dumps({"machine": machine_report(), **results}, indent=2))
        return
    for name, r in results.items():
        lat = r["latency_ms"]
        print(f"{name:24s} p50 {lat['p50']:.3f} ms  p99 {lat['p99']:.3f} ms  burst {r['burst_msgs_per_s']:.0f} msg/s")


if __name__ == "__main__":
    main()
