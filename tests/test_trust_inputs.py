"""Issue 46, cases 5 and 6: bounded reads of anything the user names. A named pipe or a device never blocks the
launcher, a recording's lying header is refused before anything is allocated, and a long recording is replayed
in constant memory."""

from __future__ import annotations

import os
import resource
import struct
import subprocess
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from agent.io.sources import ReplaySource, StreamedReplaySource, split_steps
from ecas.core.audio_file import AudioFileError, check_audio_file, load_audio
from ecas.core.config import ConfigError, load_yaml
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES
from tests.test_reliability_usage import assert_one_line_and_nothing_left, finish_usage_error, launch_cmd

ROOT = Path(__file__).resolve().parents[1]
ADDRESS_SPACE_LIMIT_BYTES = 2_500_000_000  # the measurement: 7.7 GB were allocated before


def wav_with_rate(path: Path, rate_hz: int, n_samples: int) -> Path:
    """A PCM16 mono WAV whose header declares `rate_hz` (libsndfile would write a truthful one)."""
    data = (np.sin(np.arange(n_samples) / 10) * 8000).astype("<i2").tobytes()
    fmt = struct.pack("<HHIIHH", 1, 1, rate_hz, rate_hz * 2, 2, 16)
    body = b"WAVE" + b"fmt " + struct.pack("<I", len(fmt)) + fmt + b"data" + struct.pack("<I", len(data)) + data
    path.write_bytes(b"RIFF" + struct.pack("<I", len(body)) + body)
    return path


@pytest.fixture
def talk(tmp_path) -> Path:
    path = tmp_path / "talk.wav"
    sf.write(path, np.zeros(16000, np.float32), 16000)
    return path


def start(cmd: list[str], limit_address_space: bool = False) -> subprocess.Popen:
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE_LIMIT_BYTES, resource.RLIM_INFINITY))

    return subprocess.Popen(
        cmd,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
        preexec_fn=limit if limit_address_space else None,
    )


def test_a_fifo_or_device_never_blocks_the_launcher(tmp_path, talk):
    """A config or a recording that is a named pipe with no writer, or /dev/zero: one line, exit 2."""
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    report = tmp_path / "run"
    cases = {
        "config": (launch_cmd("--replay", str(talk), "--headless", "--config", str(fifo), report=report), "config"),
        "replay": (launch_cmd("--replay", str(fifo), "--headless", report=report), "is a named pipe (FIFO)"),
        "device": (launch_cmd("--replay", "/dev/zero", "--headless", report=report), "/dev/zero: is a device"),
        "speak": (launch_cmd("--speak", str(fifo), "--headless", report=report), "is a named pipe (FIFO)"),
    }
    started = {name: start(cmd) for name, (cmd, _) in cases.items()}
    for name, proc in started.items():
        code, err, pid = finish_usage_error(proc)
        must = cases[name][1] if name != "config" else f"{fifo}: is not a regular file"
        assert_one_line_and_nothing_left(code, err, pid, must)
    assert not report.exists()


def test_load_yaml_refuses_a_fifo_without_opening_it(tmp_path):
    fifo = tmp_path / "pipe.yaml"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match="is not a regular file"):
        load_yaml(fifo)


def test_a_lying_rate_is_refused_before_anything_is_allocated(tmp_path):
    """Case 6: 160 kB at a declared 1 Hz (22 hours); the launcher runs under a 2.5 GB address-space limit."""
    lying = wav_with_rate(tmp_path / "lying.wav", 1, 80_000)
    assert lying.stat().st_size > 160_000
    proc = start(launch_cmd("--replay", str(lying), "--headless", report=tmp_path / "run"), limit_address_space=True)
    code, err, pid = finish_usage_error(proc)
    assert_one_line_and_nothing_left(code, err, pid, "its header declares 1 Hz, outside 4000-768000 Hz")
    with pytest.raises(AudioFileError, match="declares 1 Hz"):
        load_audio(lying, SAMPLE_RATE_HZ)


def test_a_recording_longer_than_the_limit_is_refused(tmp_path, monkeypatch):
    from ecas.core import audio_file

    path = tmp_path / "long.wav"
    sf.write(path, np.zeros(8000 * 5, np.float32), 8000)
    monkeypatch.setattr(audio_file, "MAX_DURATION_S", 4.0)
    with pytest.raises(AudioFileError, match=r"recordings up to .* h are replayed"):
        check_audio_file(path)


@pytest.mark.parametrize("rate_hz", [16_000, SAMPLE_RATE_HZ])
@pytest.mark.parametrize("tail_s", [0.0, 0.05, 0.5])
def test_the_streamed_replay_gives_the_steps_of_the_whole_file(tmp_path, rate_hz, tail_s):
    path = tmp_path / "talk.wav"
    rng = np.random.default_rng(0)
    sf.write(path, (0.3 * rng.standard_normal(int(rate_hz * 2.37))).astype(np.float32), rate_hz)
    whole = split_steps(load_audio(path, SAMPLE_RATE_HZ), tail_s)
    streamed = StreamedReplaySource(str(path), tail_s)
    steps = []
    while not streamed.exhausted:
        steps.append(streamed.next_block(0.0)[0])
    assert np.stack(steps).shape == whole.shape
    np.testing.assert_allclose(np.stack(steps), whole, atol=1e-4)
    assert ReplaySource(load_audio(path, SAMPLE_RATE_HZ), tail_s).blocks.shape == whole.shape


def test_a_long_recording_is_replayed_in_constant_memory(tmp_path):
    """Ten minutes at 16 kHz: a whole load is 58 MB of float32 at 24 kHz; the stream never holds a tenth of it."""
    path = tmp_path / "ten_minutes.wav"
    with sf.SoundFile(path, "w", 16000, 1, "PCM_16") as f:
        for _ in range(60):
            f.write(np.full(160_000, 0.1, np.float32))
    whole_bytes = 600 * SAMPLE_RATE_HZ * 4
    tracemalloc.start()
    try:
        source, n = StreamedReplaySource(str(path), 0.0), 0
        while not source.exhausted:
            source.next_block(0.0)
            n += 1
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert n == 600 * SAMPLE_RATE_HZ // STEP_SAMPLES
    assert peak < whole_bytes / 10, f"peak {peak / 1e6:.1f} MB"
