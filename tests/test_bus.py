"""Publisher and Subscriber in one process, on a private ipc path."""

import time

import numpy as np
import pytest
import zmq

from agent.clock import ClockSync
from agent.dashboard.events import LatencyMeter
from agent.latency import LatencyRecorder, format_table, origin_offset_ns
from ecas.core.bus import BusConfig, Publisher, Subscriber, stage_address
from ecas.core.messages import AudioUser, Command, Control, Metrics


@pytest.fixture
def pair(tmp_path):
    def make(live_queue):
        ctx = zmq.Context.instance()
        address = stage_address("io", BusConfig(), tmp_path)
        pub = Publisher(ctx, address, "io", lossless=live_queue is None)
        sub = Subscriber(ctx, [address], ["audio.user", "control"], live_queue=live_queue)
        _join(pub, sub)
        return pub, sub

    return make


def _join(pub, sub):
    """Beat until the subscriber hears the publisher (the late-joiner handshake)."""
    deadline = time.monotonic() + 5
    while not sub.controls:
        pub.send(Control(command=Command.HEARTBEAT))
        sub.socket.poll(20) and sub.poll_into_queue()
        assert time.monotonic() < deadline, "subscriber never joined"
    sub.controls.clear()


def _drain(sub, expect):
    deadline = time.monotonic() + 5
    while sub.poll_into_queue() or time.monotonic() < deadline:
        if len(sub.queue) + sub.dropped >= expect:
            break
        sub.socket.poll(20)


def block(step):
    return AudioUser(step=step, pcm=np.full(1920, step, np.float32))


def test_live_queue_drops_the_oldest_and_counts(pair):
    pub, sub = pair(live_queue=4)
    for step in range(10):
        pub.send(block(step))
    _drain(sub, 10)
    assert [m.step for m in sub.queue] == [6, 7, 8, 9]
    assert sub.dropped == 6 and sub.lost == 0


def test_kept_topics_are_never_dropped(tmp_path):
    ctx = zmq.Context.instance()
    address = stage_address("io", BusConfig(), tmp_path)
    pub = Publisher(ctx, address, "io", lossless=False)
    sub = Subscriber(ctx, [address], ["audio.user", "metrics", "control"], live_queue=3, keep_topics=["metrics"])
    _join(pub, sub)
    for step in range(6):
        pub.send(block(step))
        pub.send(Metrics(step=step))
    _drain(sub, 12)
    assert [(m.topic, m.step) for m in sub.queue] == [
        ("metrics", 0),
        ("metrics", 1),
        ("metrics", 2),
        ("audio.user", 3),
        ("metrics", 3),
        ("audio.user", 4),
        ("metrics", 4),
        ("audio.user", 5),
        ("metrics", 5),
    ]
    assert sub.dropped == 3


def test_offline_is_lossless(pair):
    pub, sub = pair(live_queue=None)
    for step in range(500):
        pub.send(block(step))
    _drain(sub, 500)
    assert [m.step for m in sub.queue] == list(range(500)) and sub.dropped == 0


def test_controls_are_never_dropped_and_gaps_are_counted_as_lost(pair):
    pub, sub = pair(live_queue=2)
    for step in range(6):
        pub.send(block(step))
        if step == 2:
            pub._seq["audio.user"] += 3  # three messages "lost upstream"
    pub.send(Control(command=Command.EOS))
    _drain(sub, 6)
    assert sub.lost == 3 and sub.dropped == 4
    assert [c.command for c in sub.controls] == [Command.EOS]


def test_tcp_and_explicit_endpoints():
    bus = BusConfig(transport="tcp", base_port=6000, endpoints={"render": "tcp://10.0.0.2:7000"})
    assert stage_address("dialogue", bus, "/unused") == "tcp://127.0.0.1:6001"
    assert stage_address("render", bus, "/unused") == "tcp://10.0.0.2:7000"


def test_clock_sync_picks_the_shortest_round_trip():
    sync = ClockSync()
    sync.add("gesture", t0=0, t1=1_000_500, t2=1_000_600, t3=2_000)  # offset ~1 ms, rtt 1.9 us
    sync.add("gesture", t0=0, t1=1_050_000, t2=1_050_100, t3=90_000)  # a slow sample
    est = sync.estimates()["gesture"]
    assert est.offset_ns == ((1_000_500 - 0) + (1_000_600 - 2_000)) // 2
    assert est.uncertainty_ns == 950 and est.samples == 2


def test_latency_splits_per_stage_and_uses_the_second_frame():
    rec = LatencyRecorder(("io", "dialogue", "gesture", "render"))
    ms = 1_000_000
    stamps = {
        "io": 1 * ms,
        "dialogue.in": 2 * ms,
        "dialogue": 12 * ms,
        "gesture.in": 13 * ms,
        "gesture": 30 * ms,
        "render.in": 31 * ms,
        "render": 60 * ms,
    }
    rec.add(Metrics(step=0, t_origin_ns=0, stamps=stamps, values={"frame_index": 0.0}), {})
    rec.add(Metrics(step=0, t_origin_ns=0, stamps=stamps, values={"frame_index": 1.0}), {"render": 5 * ms})
    summary = rec.summary({"render": {"dropped": 2}}, {})
    assert summary["steps_measured"] == 1
    assert summary["end_to_end_ms"]["p50"] == 55.0  # render's clock runs 5 ms ahead
    assert summary["stages"]["dialogue"]["compute"]["p50"] == 10.0
    assert summary["stages"]["gesture"]["wait"]["p50"] == 1.0
    assert "end to end" in format_table(summary)


def test_the_recorder_keeps_every_step_past_its_first_allocation():
    pipeline = ("io", "gesture")
    rec = LatencyRecorder(pipeline)
    ms = 1_000_000
    for step in range(3000):  # past the table's first 1024 rows: it doubles twice
        stamps = {"io": ms, "gesture.in": 2 * ms, "gesture": (3 + step % 7) * ms}
        rec.add(Metrics(step=step, t_origin_ns=0, stamps=stamps, values={}), {})
    assert rec.steps == list(range(3000))
    assert rec.e2e_ms == [3.0 + s % 7 for s in range(3000)]
    assert rec.segments_ms["gesture"]["compute"][-1] == (3 + 2999 % 7) - 2  # gesture minus gesture.in
    assert rec.summary({}, {})["steps_measured"] == 3000


def test_the_report_and_the_dashboard_measure_a_step_alike():
    pipeline = ("io", "dialogue", "gesture", "render")
    ms = 1_000_000
    stamps = {"io": 2 * ms, "dialogue.in": 3 * ms, "dialogue": 9 * ms, "gesture": 20 * ms, "render": 41 * ms}
    msg = Metrics(step=3, t_origin_ns=ms, stamps=stamps, values={"frame_index": 1.0})
    offsets = {"gesture": 2 * ms, "render": -3 * ms}  # two stages on hosts whose clocks differ
    rec = LatencyRecorder(pipeline)
    rec.add(msg, offsets)
    (event,) = LatencyMeter(pipeline, history_steps=4).on_metrics(msg, offsets)
    assert event["e2e_ms"] == rec.e2e_ms[0] == 43.0
    assert event["stages"] == {stage: rec.segments_ms[stage]["total"][0] for stage in pipeline}
    assert event["stages"]["gesture"] == 9.0 and event["stages"]["render"] == 26.0


def test_a_capture_time_moves_to_another_stage_clock_by_both_offsets():
    offsets = {"io": 5_000, "render": -2_000}  # each stage's clock minus the supervisor's
    assert origin_offset_ns("render", "io", offsets) == -7_000
    assert origin_offset_ns("render", "io", {}) == 0
