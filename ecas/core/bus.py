"""ZeroMQ PUB/SUB with typed messages: one publisher per process, subscribers to upstream processes.

Live mode keeps a bounded queue per subscriber that drops the oldest message and counts it.
Offline mode queues without limit in ZeroMQ; the source's credit window (see agent.stage) bounds what is in flight.
Every subscriber also counts messages lost upstream (gaps in a publisher's per-topic sequence numbers)
and frames it could not decode; a bad frame is logged and skipped.
"""

from __future__ import annotations

import collections
import ipaddress
import logging
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import zmq

from ecas.core.config import ConfigError
from ecas.core.messages import Control, DecodeError, Message, MsgpackSerializer, Serializer

log = logging.getLogger(__name__)

IPC_PATH_MAX = 100  # bytes of a Unix socket path (the OS limit is 107)
LIVE_HWM = 1000  # ZeroMQ's own queue in live mode; our bounded deque does the dropping

STAGES = ("io", "dialogue", "gesture", "render")  # the pipeline, upstream first


@dataclass(frozen=True)
class BusConfig:
    """Where each process publishes, and how the bus behaves.

    `transport: ipc` binds `ipc://<private run dir>/<stage>.sock`; `tcp` binds `tcp://<host>:<base_port + i>`;
    `base_port: 0` gives every endpoint a free port (one host runs every stage), so tcp runs never collide.
    `endpoints` pins a stage to an explicit address (`tcp://gpu-box:5601`) to split the loop across hosts.
    A stage fails the run when its handler fails on `max_handler_failures` messages in a row, or when it
    publishes nothing for `stall_timeout_s` while its upstream stage is ahead of it (a heartbeat alone does
    not count as progress).
    """

    transport: Literal["ipc", "tcp"] = "ipc"
    host: str = "127.0.0.1"
    base_port: int = 5600
    endpoints: dict[str, str] = field(default_factory=dict)
    live_queue_steps: int = 4
    credit_window_steps: int = 32
    heartbeat_s: float = 0.25
    heartbeat_timeout_s: float = 15.0
    ready_timeout_s: float = 180.0
    stop_timeout_s: float = 1.5
    max_handler_failures: int = 16
    stall_timeout_s: float = 30.0

    def __post_init__(self):
        if not 0 <= self.base_port <= 65535 - len(STAGES) - 2:
            raise ConfigError(
                f"bus.base_port: must be a tcp port (1-{65535 - len(STAGES) - 2}), or 0 for free "
                f"ports; got {self.base_port}"
            )
        for name in ("stall_timeout_s", "ready_timeout_s", "stop_timeout_s"):
            if not getattr(self, name) > 0:  # a stop timeout of 0 or less would SIGTERM every stage at once
                raise ConfigError(f"bus.{name}: must be > 0, got {getattr(self, name)}")
        for name in ("live_queue_steps", "credit_window_steps", "max_handler_failures"):
            if getattr(self, name) < 1:
                raise ConfigError(f"bus.{name}: must be >= 1, got {getattr(self, name)}")
        if not 0 < self.heartbeat_s < self.heartbeat_timeout_s:
            raise ConfigError("bus.heartbeat_s: must be > 0 and below bus.heartbeat_timeout_s")
        unknown = sorted(set(self.endpoints) - set(STAGES) - {"supervisor", "dashboard"})
        if unknown:
            raise ConfigError(f"bus.endpoints.{unknown[0]}: unknown stage (stages: {', '.join(STAGES)})")
        for stage, address in self.endpoints.items():
            if not address.startswith(("tcp://", "ipc://")):
                raise ConfigError(f"bus.endpoints.{stage}: expected tcp://host:port or ipc://path, got {address!r}")


def stage_address(stage: str, bus: BusConfig, ipc_dir: Path) -> str:
    """The address `stage` publishes on (and its subscribers connect to)."""
    if stage in bus.endpoints:
        return bus.endpoints[stage]
    if bus.transport == "tcp":
        index = (*STAGES, "supervisor", "dashboard").index(stage)
        return f"tcp://{bus.host}:{bus.base_port + index}"
    path = str(Path(ipc_dir) / f"{stage}.sock")
    if len(path.encode()) > IPC_PATH_MAX:
        raise ValueError(f"ipc path too long for a Unix socket ({len(path)} bytes): {path}")
    return f"ipc://{path}"


def bus_addresses(bus: BusConfig, ipc_dir: Path) -> dict[str, str]:
    """The address of every process that publishes: each stage, the supervisor and the dashboard."""
    return {name: stage_address(name, bus, ipc_dir) for name in (*STAGES, "supervisor", "dashboard")}


def beyond_loopback(address: str) -> bool:
    """True for a tcp address other machines can reach (a wildcard, a name, a non-loopback IP); an ipc socket is
    a file in the run's private directory."""
    if not address.startswith("tcp://"):
        return False
    host = address[len("tcp://") :].rpartition(":")[0].strip("[]")
    if host == "localhost":
        return False
    try:
        return not ipaddress.ip_address(host).is_loopback
    except ValueError:  # "*", a host or interface name
        return True


def address_option(name: str, bus: BusConfig) -> str:
    """The option that decides where `name` listens (an endpoint on `bus.host` was given a free port from it)."""
    endpoint = bus.endpoints.get(name)
    if endpoint is None or endpoint[len("tcp://") :].rpartition(":")[0] == bus.host:
        return "bus.host"
    return f"bus.endpoints.{name}"


class Publisher:
    """Binds one PUB socket and numbers each topic's messages (`seq`), so receivers can count losses."""

    def __init__(
        self, ctx: zmq.Context, address: str, source: str, *, lossless: bool, serializer: Serializer | None = None
    ):
        self.source = source
        self.serializer = serializer or MsgpackSerializer()
        self.socket = ctx.socket(zmq.PUB)
        self.socket.setsockopt(zmq.SNDHWM, 0 if lossless else LIVE_HWM)
        self.socket.setsockopt(zmq.LINGER, 500)
        self.socket.bind(address)
        self._seq: dict[str, int] = collections.defaultdict(int)

    def send(self, msg: Message) -> None:
        msg.source = self.source
        msg.seq = self._seq[msg.topic]
        self._seq[msg.topic] += 1
        self.socket.send_multipart(self.serializer.encode(msg), copy=False)

    def close(self) -> None:
        self.socket.close()


class Subscriber:
    """One SUB socket connected to several publishers, decoding into typed messages.

    Control messages go to their own queue, which is never dropped. A publisher's messages arrive in the
    order it sent them, so when its EOS is taken from `controls`, all its data is already in `queue`.
    In live mode at most `live_queue` messages wait, dropping the oldest; messages of `keep_topics` (small ones
    whose every instance matters, such as the dialogue's words) are neither counted nor dropped.
    """

    def __init__(
        self,
        ctx: zmq.Context,
        addresses: Iterable[str],
        topics: Iterable[str],
        *,
        live_queue: int | None,
        keep_topics: Iterable[str] = (),
        serializer: Serializer | None = None,
    ):
        self.serializer = serializer or MsgpackSerializer()
        self.socket = ctx.socket(zmq.SUB)
        self.socket.setsockopt(zmq.RCVHWM, LIVE_HWM if live_queue else 0)
        self.socket.setsockopt(zmq.LINGER, 0)
        for topic in topics:
            self.socket.setsockopt(zmq.SUBSCRIBE, topic.encode())
        for address in addresses:
            self.socket.connect(address)
        self.queue: collections.deque[Message] = collections.deque()  # data, in arrival order
        self.controls: collections.deque[Control] = collections.deque()  # never dropped
        self.live_queue = live_queue
        self.keep_topics = frozenset(keep_topics)
        self.dropped = 0  # dropped here, oldest first, because the consumer fell behind (live mode)
        self.lost = 0  # never arrived: gaps in the publishers' sequence numbers
        self.decode_errors = 0
        self._next_seq: dict[tuple[str, str], int] = {}

    def poll_into_queue(self) -> int:
        """Move every frame ZeroMQ holds into the queue; return how many messages arrived."""
        arrived = 0
        while True:
            try:
                frames = self.socket.recv_multipart(zmq.NOBLOCK, copy=False)
            except zmq.Again:
                return arrived
            msg = self._decode([f.buffer for f in frames])
            if msg is not None:
                self._count_gap(msg)
                self._enqueue(msg)
                arrived += 1

    def _decode(self, frames) -> Message | None:
        try:
            return self.serializer.decode(frames)
        except DecodeError as e:
            self.decode_errors += 1
            log.warning("skipped a malformed frame on topic %r: %s", bytes(frames[0])[:40], e)
            return None

    def _count_gap(self, msg: Message) -> None:
        key = (msg.source, msg.topic)
        expected = self._next_seq.get(key)
        if expected is not None and msg.seq > expected:
            self.lost += msg.seq - expected
        self._next_seq[key] = msg.seq + 1

    def _enqueue(self, msg: Message) -> None:
        if isinstance(msg, Control):
            self.controls.append(msg)
            return
        self.queue.append(msg)
        if self.live_queue and msg.topic not in self.keep_topics:
            droppable = [i for i, m in enumerate(self.queue) if m.topic not in self.keep_topics]
            if len(droppable) > self.live_queue:
                del self.queue[droppable[0]]
                self.dropped += 1

    def close(self) -> None:
        self.socket.close()
