import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from agent.io.sources import NoAudioDevice, ReplaySource, check_input_device, split_steps
from ecas.core.audio_file import AudioFileError, load_audio
from ecas.core.paths import data_root
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES

ROOT = Path(__file__).resolve().parents[1]
SHARED = data_root()


@pytest.mark.parametrize(
    "fmt, subtype, rate, channels",
    [
        ("WAV", "PCM_16", 16000, 1),
        ("WAV", "PCM_32", 44100, 2),
        ("WAV", "FLOAT", 24000, 1),
        ("FLAC", "PCM_16", 48000, 2),
        ("OGG", "VORBIS", 22050, 1),
    ],
)
def test_any_libsndfile_format_becomes_24k_mono(tmp_path, fmt, subtype, rate, channels):
    t = np.arange(rate) / rate  # 1 s
    tone = 0.5 * np.sin(2 * np.pi * 440 * t)
    data = np.stack([tone] * channels, axis=1)
    path = tmp_path / f"x.{fmt.lower()}"
    sf.write(path, data, rate, format=fmt, subtype=subtype)
    pcm = load_audio(path, SAMPLE_RATE_HZ)
    assert pcm.dtype == np.float32 and pcm.ndim == 1
    assert abs(len(pcm) - SAMPLE_RATE_HZ) <= 2
    assert 0.3 < np.abs(pcm).max() <= 0.55  # the level survives, channels are averaged not summed
    spectrum = np.abs(np.fft.rfft(pcm))
    assert abs(np.argmax(spectrum) * SAMPLE_RATE_HZ / len(pcm) - 440) < 3


def test_real_float32_beat2_wav():
    pcm = load_audio(SHARED / "beat2" / "2_scott_0_1_1.wav", SAMPLE_RATE_HZ)
    assert 63 < len(pcm) / SAMPLE_RATE_HZ < 65
    assert np.abs(pcm).max() > 0.05


def _bad_files(tmp: Path) -> dict[str, tuple[Path, str]]:
    (tmp / "empty.wav").write_bytes(b"")
    (tmp / "corrupt.wav").write_bytes(b"RIFF\x10\x00\x00\x00WAVEfmt garbage")
    (tmp / "notes.ogg").write_text("this is text, not audio\n" * 10)
    sf.write(tmp / "zero.wav", np.zeros((0, 1), np.float32), 16000)
    return {
        "missing": (tmp / "missing.wav", "no such file"),
        "empty": (tmp / "empty.wav", "the file is empty"),
        "corrupt": (tmp / "corrupt.wav", "not a readable audio file"),
        "unsupported": (tmp / "notes.ogg", "not a readable audio file"),
        "no samples": (tmp / "zero.wav", "contains no audio samples"),
        "directory": (tmp, "is a directory"),
    }


@pytest.mark.parametrize("case", ["missing", "empty", "corrupt", "unsupported", "no samples", "directory"])
def test_bad_files_give_one_clear_error(tmp_path, case):
    path, message = _bad_files(tmp_path)[case]
    with pytest.raises(AudioFileError, match=message):
        load_audio(path, SAMPLE_RATE_HZ)


@pytest.mark.parametrize("case", ["missing", "corrupt", "unsupported"])
def test_launch_exits_2_with_one_line_for_a_bad_recording(tmp_path, case):
    path, message = _bad_files(tmp_path)[case]
    proc = subprocess.run(
        [sys.executable, "launch.py", "--replay", str(path), "--headless"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and message in lines[0]


def test_no_audio_device_suggests_replay():
    try:
        check_input_device(None)
    except NoAudioDevice:
        pass
    else:
        pytest.skip("this machine has a working microphone")
    proc = subprocess.run([sys.executable, "launch.py", "--mic"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "use --replay FILE" in proc.stderr and proc.stderr.count("\n") == 1


def test_replay_is_split_into_whole_steps_with_a_silent_tail():
    pcm = np.ones(STEP_SAMPLES * 2 + 10, np.float32)
    blocks = split_steps(pcm, tail_silence_s=0.16)
    assert blocks.shape == (5, STEP_SAMPLES)  # 2 full steps, 1 partial, 2 of silence (4 steps of samples → 5)
    assert blocks[2, :10].min() == 1 and blocks[2, 10:].max() == 0 and blocks[3:].max() == 0
    source = ReplaySource(pcm, 0.0)
    got = []
    while not source.exhausted:
        got.append(source.next_block(0)[0])
    np.testing.assert_array_equal(np.concatenate(got)[: len(pcm)], pcm)


class FakeStreamTime:
    def __init__(self, now_s, adc_s):
        self.currentTime, self.inputBufferAdcTime = now_s, adc_s


class FakeSoundDevice:
    """Stands in for PortAudio (no sound card here): records the streams it opens."""

    def __init__(self):
        self.streams = []

    def InputStream(self, **kw):
        return self._stream(kw)

    def OutputStream(self, **kw):
        return self._stream(kw)

    def _stream(self, kw):
        stream = type("Stream", (), {"start": lambda s: None, "stop": lambda s: None, "close": lambda s: None})()
        stream.kw = kw
        self.streams.append(stream)
        return stream


def test_microphone_delivers_80ms_blocks_stamped_at_their_last_sample(monkeypatch):
    import time

    from agent.io import sources

    fake = FakeSoundDevice()
    monkeypatch.setattr(sources, "_sounddevice", lambda: fake)
    mic = sources.MicSource(device=None)
    kw = fake.streams[0].kw
    assert (kw["samplerate"], kw["blocksize"], kw["channels"]) == (SAMPLE_RATE_HZ, STEP_SAMPLES, 1)
    block = np.random.default_rng(0).standard_normal((STEP_SAMPLES, 1)).astype(np.float32)
    before = time.monotonic_ns()
    kw["callback"](block, STEP_SAMPLES, FakeStreamTime(10.0, 9.9), None)  # first sample captured 100 ms ago
    pcm, captured_ns = mic.next_block(timeout_s=1)
    np.testing.assert_array_equal(pcm, block[:, 0])
    expected = before - 100_000_000 + (STEP_SAMPLES - 1) * 1_000_000_000 // SAMPLE_RATE_HZ
    assert abs(captured_ns - expected) < 20_000_000
    assert mic.next_block(timeout_s=0.01) is None


def test_speaker_plays_steps_in_order_and_drops_the_oldest_when_far_behind(monkeypatch):
    from agent.io import sources
    from agent.io import speaker as speaker_module

    fake = FakeSoundDevice()
    monkeypatch.setattr(sources, "_sounddevice", lambda: fake)
    monkeypatch.setattr(speaker_module, "_sounddevice", lambda: fake)
    out = speaker_module.Speaker(device=None)
    fill = fake.streams[0].kw["callback"]
    out.play(np.full(STEP_SAMPLES, 0.1, np.float32))
    out.play(np.full(STEP_SAMPLES, 0.2, np.float32))
    buf = np.zeros((STEP_SAMPLES + 100, 1), np.float32)
    fill(buf, len(buf), None, None)
    assert np.all(buf[:STEP_SAMPLES, 0] == np.float32(0.1)) and np.all(buf[STEP_SAMPLES:, 0] == np.float32(0.2))
    for _ in range(speaker_module.MAX_BUFFER_STEPS + 3):
        out.play(np.ones(STEP_SAMPLES, np.float32))
    assert out.dropped_samples > 0


def test_a_truncated_wav_is_read_with_a_warning(tmp_path, caplog):
    full = tmp_path / "full.wav"
    sf.write(
        full, (0.3 * np.sin(np.arange(32000) / 16000 * 2 * np.pi * 220)).astype(np.float32), 16000, subtype="PCM_16"
    )  # 2 s
    cut = tmp_path / "cut.wav"
    cut.write_bytes(full.read_bytes()[: 44 + 16000 * 2 // 2])  # the header and 0.5 s of samples
    with caplog.at_level("WARNING", logger="ecas.core.audio_file"):
        pcm = load_audio(cut, SAMPLE_RATE_HZ)
        load_audio(full, SAMPLE_RATE_HZ)
    assert abs(len(pcm) - SAMPLE_RATE_HZ // 2) <= 2
    assert [r.getMessage() for r in caplog.records] == [
        f"{cut}: truncated WAV: its header declares 2.00 s of audio, the file holds 0.50 s"
    ]


def test_samples_beyond_full_scale_are_read_with_a_warning(tmp_path, caplog):
    loud = tmp_path / "loud.wav"
    sf.write(loud, np.array([0.5, 1.5, -2.0, 0.0] * 4000, np.float32), 16000, subtype="FLOAT")
    with caplog.at_level("WARNING", logger="ecas.core.audio_file"):
        load_audio(loud, SAMPLE_RATE_HZ)
    assert [r.getMessage() for r in caplog.records] == [
        f"{loud}: 8000 samples beyond ±1 full scale (peak 2.00); they clip when played or encoded"
    ]
