"""The motion stream's wire format: round trips, the documented byte layout, and packets it must refuse."""

from __future__ import annotations

import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ecas.core.body import NUM_EXPRESSIONS, NUM_JOINTS
from render.arkit import arkit_weights
from render.motion_wire import (
    FRAME_BYTES,
    HEADER_BYTES,
    MAGIC,
    VERSION,
    WireError,
    decode,
    encode,
    motion_packet,
)
from tests.test_runtime import finish, launch, leftovers, talk  # noqa: F401  (talk: a fixture)

REPO = Path(__file__).resolve().parents[1]


def _packet(step: int = 7, n: int = 2, seed: int = 0):
    rng = np.random.default_rng(seed)
    return motion_packet(
        step,
        rng.normal(0, 0.3, (n, NUM_JOINTS, 3)),
        rng.normal(0, 1, (n, 3)),
        rng.normal(0, 1, (n, NUM_EXPRESSIONS)),
        t_origin_ns=123_456_789_012,
        t_motion_ns=123_456_999_000,
    )


def test_round_trip_is_exact():
    packet = _packet()
    data = encode(packet)
    assert len(data) == HEADER_BYTES + 2 * FRAME_BYTES == 48 + 2 * 1280
    back = decode(data)
    assert back.step == 7 and back.n_frames == 2 and back.first_frame == 14 and back.fps == 25.0
    assert back.t_origin_ns == packet.t_origin_ns and back.t_motion_ns == packet.t_motion_ns
    for name in ("poses", "trans", "expressions", "arkit"):
        assert np.array_equal(getattr(back, name), getattr(packet, name)), name
        assert getattr(back, name).dtype == np.float32
    assert encode(back) == data
    assert decode(bytearray(data)).step == 7 and decode(memoryview(data)).step == 7


def test_the_bytes_are_where_the_document_says():
    packet = _packet(step=1000, n=3)
    data = encode(packet)
    assert data[:4] == b"ECMS" == MAGIC
    assert struct.unpack_from("<HHI", data, 4) == (VERSION, 3, 1000)
    assert struct.unpack_from("<HHHH", data, 12) == (55, 100, 52, 0)
    assert struct.unpack_from("<f", data, 20) == (25.0,)
    assert struct.unpack_from("<qqII", data, 24) == (123_456_789_012, 123_456_999_000, 2000, 0)
    second = HEADER_BYTES + FRAME_BYTES  # the second frame: rotations, translation, expressions, ARKit
    floats = np.frombuffer(data, "<f4", count=320, offset=second)
    assert np.array_equal(floats[:165], packet.poses[1].ravel())
    assert np.array_equal(floats[165:168], packet.trans[1])
    assert np.array_equal(floats[168:268], packet.expressions[1])
    assert np.array_equal(floats[268:320], packet.arkit[1])


def test_arkit_weights_are_computed_from_the_face_when_not_given():
    packet = _packet()
    assert np.array_equal(packet.arkit, arkit_weights(packet.expressions, packet.poses[:, 22]))
    given = motion_packet(0, packet.poses, packet.trans, packet.expressions, arkit=np.full((2, 52), 0.5))
    assert np.all(decode(encode(given)).arkit == 0.5)


def test_another_version_is_refused_clearly():
    data = bytearray(encode(_packet()))
    struct.pack_into("<H", data, 4, VERSION + 1)
    with pytest.raises(WireError, match=f"version {VERSION + 1}; this reader reads version {VERSION} only"):
        decode(bytes(data))


def test_malformed_packets_are_refused():
    data = encode(_packet())
    with pytest.raises(WireError, match="magic"):
        decode(b"JPEG" + data[4:])
    with pytest.raises(WireError, match="expected 2608"):
        decode(data[:-4])
    with pytest.raises(WireError, match="header"):
        decode(data[:20])
    wrong = bytearray(data)
    struct.pack_into("<H", wrong, 12, 24)
    with pytest.raises(WireError, match="24 joints"):
        decode(bytes(wrong))
    with pytest.raises(WireError, match="trans"):
        motion_packet(0, np.zeros((2, 55, 3)), np.zeros((3, 3)), np.zeros((2, 100)))
    with pytest.raises(WireError, match="arkit"):
        motion_packet(0, np.zeros((2, 55, 3)), np.zeros((2, 3)), np.zeros((2, 100)), arkit=np.zeros((2, 51)))


def test_a_run_streams_every_step_to_the_python_client(tmp_path, talk):
    """A real run (launch.py, the test stages): the example client subscribes, starts the run and saves every step."""
    wav, n_steps = talk
    report = tmp_path / "run"
    proc = launch(["--replay", str(wav), "--set", "dashboard.wait_for_start=true"], report)
    out = tmp_path / "motion.npz"
    try:
        url_file = report / "dashboard.url"
        deadline = time.monotonic() + 90
        while not (url_file.exists() and url_file.read_text().strip()):
            assert proc.poll() is None and time.monotonic() < deadline, "the dashboard did not start"
            time.sleep(0.05)
        client = subprocess.run(
            [sys.executable, str(REPO / "examples" / "motion_client.py"), url_file.read_text().strip()]
            + ["--start", "--save", str(out)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        code, output = finish(proc, timeout_s=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert client.returncode == 0, client.stderr
    assert code == 0, output
    assert leftovers(proc.pid) == []
    saved = np.load(out)
    steps = saved["steps"]
    assert steps.tolist() == list(range(n_steps)), "a step is missing"  # none dropped, in order
    poses = saved["poses"].reshape(-1, 55, 3)
    assert poses.shape == (2 * n_steps, 55, 3) and saved["arkit"].shape == (2 * n_steps, 52)
    assert np.allclose(poses[::2, 17, 2], np.sin(steps * 0.1), atol=1e-6)  # tests.components.WaveGesture's arm
    assert float(saved["mocap_frame_rate"]) == 25.0
    lines = client.stdout.splitlines()
    assert len(lines) == n_steps and lines[0].startswith("step     0")
