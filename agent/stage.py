"""The generic stage process: sockets, readiness handshake, heartbeats, stamps, drops, credits, end of stream.

A stage supplies a `Component` (and the io stage also a `Source`). The runner:
- subscribes to its upstream stages' data topics and everyone's `control`;
- reports READY in its heartbeats once it has heard every upstream publisher and the supervisor, so ZeroMQ's
  late-joiner loss can never eat the first step; the source starts only on the supervisor's START;
- copies step, t_origin_ns and stamps from each input to its outputs and stamps `<stage>.in` / `<stage>`;
- in offline mode, lets the source run at most `credit_window_steps` ahead of the sink, blocking on the socket
  (never spinning) while it waits for the sink's PROGRESS;
- logs and skips a message whose handler raises, and carries on; a handler that raises `StageFailed` (its output
  cannot be written), or fails on `bus.max_handler_failures` messages in a row, fails the stage: it stops
  handling data and reports the error in its heartbeats, and the supervisor ends the run with it.

Heartbeats carry the stage's counters, among them `progress_step` (the last step it published; live, also the
last step it handled, since a live stage may drop late work on purpose) and `cpu_s` (its
process's CPU time), and the partial files its component is writing, so the supervisor can detect a stage
that makes no progress while its input waits, and remove a killed stage's partial files.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import zmq

from agent.latency import origin_offset_ns
from agent.sections import AppConfig
from ecas.core.bus import Publisher, Subscriber, stage_address
from ecas.core.component import Component, RunContext, Source, StageFailed
from ecas.core.messages import AudioUser, Command, Control, Kind, Message, Metrics, StageState
from ecas.core.timing import NS_PER_MS, STEP_NS

log = logging.getLogger(__name__)

OUTPUT_TOPIC = {
    "io": Kind.AUDIO_USER.value,
    "dialogue": Kind.DIALOGUE_STEP.value,
    "gesture": Kind.GESTURE_STEP.value,
    "render": Kind.RENDER_FRAME.value,
}
DATA_INPUTS = {  # stage -> {upstream stage: topic}; the io stage's speaker input is added when enabled
    "dialogue": {"io": OUTPUT_TOPIC["io"]},
    "gesture": {"dialogue": OUTPUT_TOPIC["dialogue"]},
    "render": {"dialogue": OUTPUT_TOPIC["dialogue"], "gesture": OUTPUT_TOPIC["gesture"]},
}
SUPERVISOR = "supervisor"
MAX_POLL_MS = 50


@dataclass(frozen=True)
class Topology:
    """Who this stage listens to, derived from the run's pipeline."""

    stage: str
    pipeline: tuple[str, ...]
    data_inputs: dict[str, str] = field(default_factory=dict)

    @classmethod
    def of(cls, stage: str, pipeline: Sequence[str], speaker: bool = False) -> Topology:
        inputs = {up: topic for up, topic in DATA_INPUTS.get(stage, {}).items() if up in pipeline}
        if stage == "io" and speaker and "dialogue" in pipeline:
            inputs["dialogue"] = OUTPUT_TOPIC["dialogue"]
        return cls(stage, tuple(pipeline), inputs)

    @property
    def sink(self) -> str:
        return self.pipeline[-1]

    @property
    def sink_primary_topic(self) -> str | None:
        return OUTPUT_TOPIC[self.pipeline[-2]] if len(self.pipeline) > 1 else None

    @property
    def peers(self) -> set[str]:
        """Publishers this stage must hear before it is ready."""
        peers = set(self.data_inputs) | {SUPERVISOR}
        if self.stage == "io" and self.sink != "io":
            peers.add(self.sink)  # the sink's PROGRESS drives the offline credit window
        return peers


class StageRunner:
    def __init__(
        self,
        topology: Topology,
        app: AppConfig,
        run: RunContext,
        ipc_dir: Path,
        component: Component,
        source: Source | None = None,
    ):
        self.name = topology.stage
        self.topology = topology
        self.bus = app.bus
        self.run_ctx = run
        self.component = component
        self.source = source
        self.ctx = zmq.Context.instance()
        self.pub = Publisher(self.ctx, stage_address(self.name, self.bus, ipc_dir), self.name, lossless=not run.live)
        topics = [Kind.CONTROL.value, *set(topology.data_inputs.values())]
        addresses = [stage_address(peer, self.bus, ipc_dir) for peer in sorted(topology.peers)]
        queue = self.bus.live_queue_steps * max(1, len(topology.data_inputs))  # steps of every input topic
        self.sub = Subscriber(self.ctx, addresses, topics, live_queue=queue if run.live else None)
        self.state = StageState.STARTING
        self.heard: set[str] = set()
        self.eos_from: set[str] = set()
        self.started = False
        self.stopping = False
        self.handler_errors = 0
        self.failures_in_a_row = 0
        self.fatal_error: str | None = None
        self.handled = 0
        self.progress_step = -1
        self.published = 0  # messages on the stage's output topic
        self.next_step = 0
        self.source_t0_ns = 0
        self.sink_progress = -1
        self._next_heartbeat_ns = 0

    # ---- main loop -------------------------------------------------------------------------------------------
    def run(self) -> None:
        try:
            while not self.stopping:
                self._poll(self._poll_timeout_ms())
                self._take_controls()
                if self.fatal_error is not None:
                    self.sub.queue.clear()  # a failed stage takes no more data; the supervisor stops the run
                elif self.started and self.source is not None and self.state != StageState.DONE:
                    self._emit_source()
                if self.sub.queue:
                    self._handle(self.sub.queue.popleft())
                self._check_end_of_stream()
                self._heartbeat()
        finally:
            self._close()

    def request_stop(self) -> None:
        self.stopping = True

    def _poll(self, timeout_ms: int) -> None:
        if self.sub.queue and timeout_ms > 0:
            timeout_ms = 0
        if self.sub.socket.poll(timeout_ms, zmq.POLLIN):
            self.sub.poll_into_queue()
        if os.getppid() == 1:  # the supervisor died without stopping us
            log.error("supervisor is gone; stopping")
            self.stopping = True

    def _poll_timeout_ms(self) -> int:
        """How long to block on the socket: until the next source block is due, or for news (data, PROGRESS)."""
        if self.source is None or not self.started or self.state == StageState.DONE or self.fatal_error:
            return MAX_POLL_MS
        if self.source.paced:
            return 0  # the source's own next_block waits for the device
        if self._waiting_for_credit():
            return MAX_POLL_MS  # the sink's PROGRESS arrives on the socket and ends the wait
        return min(MAX_POLL_MS, max(0, math.ceil(self._due_in_ms())))

    # ---- control ---------------------------------------------------------------------------------------------
    def _take_controls(self) -> None:
        while self.sub.controls:
            msg = self.sub.controls.popleft()
            self.heard.add(msg.source)
            if msg.source == SUPERVISOR:
                self._supervisor_command(msg)
            elif msg.command == Command.EOS and msg.source in self.topology.data_inputs:
                self.eos_from.add(msg.source)
            elif msg.command == Command.PROGRESS and msg.source == self.topology.sink:
                self.sink_progress = max(self.sink_progress, msg.detail["step"])
        if self.state == StageState.STARTING and self.heard >= self.topology.peers:
            self.state = StageState.READY
            self._next_heartbeat_ns = 0
            log.info("ready")

    def _supervisor_command(self, msg: Control) -> None:
        if msg.command == Command.START and self.state == StageState.READY:
            self.state = StageState.RUNNING
            self.started = True
            self.source_t0_ns = time.monotonic_ns()
            set_offset = getattr(self.component, "set_origin_offset_ns", None)  # ecas.core.component.ClockAware
            if set_offset is not None:
                set_offset(
                    origin_offset_ns(self.name, self.topology.pipeline[0], msg.detail.get("clock_offsets_ns", {}))
                )
        elif msg.command == Command.STOP and not self.stopping:
            log.info("stopping")
            self.stopping = True
        elif msg.command == Command.PING and msg.detail.get("to") == self.name:
            t1 = time.monotonic_ns()
            self.pub.send(Control(command=Command.PONG, detail={**msg.detail, "t1": t1, "t2": time.monotonic_ns()}))

    def _heartbeat(self) -> None:
        now = time.monotonic_ns()
        if now < self._next_heartbeat_ns:
            return
        self._next_heartbeat_ns = now + int(self.bus.heartbeat_s * 1e9)
        self.pub.send(Control(command=Command.HEARTBEAT, detail=self._heartbeat_detail(self.state.value)))

    def _heartbeat_detail(self, state: str) -> dict:
        detail = {"state": state, "counters": self.counters(), "partial_files": self._partial_files()}
        if self.fatal_error is not None:
            detail["error"] = self.fatal_error
        return detail

    def _partial_files(self) -> list[str]:
        partial = getattr(self.component, "partial_files", None)
        return [str(p) for p in partial()] if callable(partial) else []

    def counters(self) -> dict[str, int | float]:
        counters = {
            "dropped": self.sub.dropped,
            "lost": self.sub.lost,
            "decode_errors": self.sub.decode_errors,
            "handler_errors": self.handler_errors,
            "handled": self.handled,
            "sent_steps": self.next_step,
            "published": self.published,
            "progress_step": self.progress_step,
            "cpu_s": round(time.process_time(), 3),
        }
        extra = getattr(self.component, "counters", None)
        if callable(extra):
            counters.update(extra())
        return counters

    # ---- data ------------------------------------------------------------------------------------------------
    def _handle(self, msg: Message) -> None:
        msg.stamps[f"{self.name}.in"] = time.monotonic_ns()
        self.handled += 1
        try:
            outputs = self.component.handle(msg)
        except StageFailed as e:
            self._fail(str(e))
            return
        except Exception as e:
            self.handler_errors += 1
            self.failures_in_a_row += 1
            log.exception("handler failed on %s step %d from %s; skipped", msg.topic, msg.step, msg.source)
            if self.failures_in_a_row >= self.bus.max_handler_failures:
                self._fail(
                    f"the handler failed on {self.failures_in_a_row} messages in a row; the last: "
                    f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
                )
            return
        self.failures_in_a_row = 0
        if self.run_ctx.live:
            self.progress_step = max(self.progress_step, msg.step)
        for out in outputs:
            out.session, out.step, out.t_origin_ns = msg.session, msg.step, msg.t_origin_ns
            out.stamps = {**msg.stamps, self.name: time.monotonic_ns()}
            self._publish(out)
        if self.name == self.topology.sink and msg.topic == self.topology.sink_primary_topic:
            self.pub.send(Control(command=Command.PROGRESS, detail={"step": msg.step}))

    def _fail(self, error: str) -> None:
        """Stop taking data and tell the supervisor now (and in every later heartbeat)."""
        self.fatal_error = error
        log.error("failed: %s", error)
        self._next_heartbeat_ns = 0

    def _publish(self, out: Message) -> None:
        self.pub.send(out)
        if out.topic == OUTPUT_TOPIC[self.name]:
            self.progress_step = max(self.progress_step, out.step)
            self.published += 1
        if self.name == self.topology.sink:
            frame_index = getattr(out, "frame_index", 0)
            self.pub.send(
                Metrics(
                    session=out.session,
                    step=out.step,
                    t_origin_ns=out.t_origin_ns,
                    stamps=out.stamps,
                    values={"frame_index": float(frame_index)},
                )
            )

    def _check_end_of_stream(self) -> None:
        if self.state != StageState.RUNNING or self.source is not None:
            return
        if self.eos_from >= set(self.topology.data_inputs) and not self.sub.queue:
            self._finish()

    def _finish(self) -> None:
        try:
            flushed = self.component.flush()
        except StageFailed as e:
            self._fail(str(e))
            return
        for out in flushed:
            out.session = self.run_ctx.session
            out.stamps = {**out.stamps, self.name: time.monotonic_ns()}
            self._publish(out)
        self.state = StageState.DONE
        self.pub.send(Control(command=Command.EOS, detail=self.counters()))
        self._next_heartbeat_ns = 0
        log.info("end of stream")

    # ---- source (the io stage) -------------------------------------------------------------------------------
    def _due_in_ms(self) -> float:
        """Until the step's last sample is 'captured' (live replay); never early, so t_origin is in the past."""
        due_ns = self.source_t0_ns + (self.next_step + 1) * STEP_NS
        return (due_ns - time.monotonic_ns()) / NS_PER_MS if self.run_ctx.live else 0.0

    def _waiting_for_credit(self) -> bool:
        """Offline: the source is a whole credit window ahead of the sink."""
        return not self.run_ctx.live and self.next_step - self.sink_progress > self.bus.credit_window_steps

    def _emit_source(self) -> None:
        if self.source.exhausted:
            self._finish()
            return
        if self._waiting_for_credit():
            return
        if not self.source.paced and self._due_in_ms() > 0:
            return
        block = self.source.next_block(timeout_s=0.005 if self.source.paced else 0.0)
        if block is None:
            return
        pcm, captured_ns = block
        if captured_ns is None:
            captured_ns = (
                (self.source_t0_ns + (self.next_step + 1) * STEP_NS) if self.run_ctx.live else time.monotonic_ns()
            )
        msg = AudioUser(session=self.run_ctx.session, step=self.next_step, t_origin_ns=captured_ns, pcm=pcm)
        msg.stamps = {self.name: time.monotonic_ns()}
        self._publish(msg)
        self.next_step += 1

    def _close(self) -> None:
        start_s = time.monotonic()
        try:
            self.component.close()
            log.info("closed in %.2f s", time.monotonic() - start_s)
        finally:
            if self.source is not None:
                self.source.close()
            self.state = StageState.DONE
            self.pub.send(Control(command=Command.HEARTBEAT, detail=self._heartbeat_detail("done")))
            self.pub.close()
            self.sub.close()
