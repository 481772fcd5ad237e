"""MP4 output: the writer (codecs, exact A/V lengths, no partial files), render.play on the BEAT2 clip, and the
render stage component writing the conversation with its audio."""

import numpy as np
import pytest
import torch

from ecas.core.component import RunContext
from ecas.core.messages import DialogueStep, GestureStep
from ecas.core.timing import FRAME_SAMPLES, SAMPLE_RATE_HZ, STEP_SAMPLES
from render.config import RenderConfig
from render.mp4 import BackgroundMp4Writer, Mp4Error, Mp4Writer
from tests.data.beat2_clip import CLIP_NPZ, CLIP_WAV, needs_clip
from tests.render_helpers import (
    check_av_sync,
    decode,
    needs_osmesa,
    silhouette,
    silhouette_center,
)

torch.set_num_threads(1)


def test_writer_streams_lengths_and_content(tmp_path):
    path = tmp_path / "out.mp4"
    tone = (0.5 * np.sin(2 * np.pi * 440 * np.arange(50 * FRAME_SAMPLES) / SAMPLE_RATE_HZ)).astype(np.float32)
    with Mp4Writer(path, 64, 48) as writer:
        for i in range(50):
            writer.write(np.full((48, 64, 3), 5 * i, np.uint8), tone[i * FRAME_SAMPLES : (i + 1) * FRAME_SAMPLES])
    info = decode(path)
    check_av_sync(info, 50)
    assert info["audio_rate"] == SAMPLE_RATE_HZ and info["audio_channels"] == 1
    assert abs(info["frames"][40].mean() - 200) < 6  # the frames keep their order
    rms = np.sqrt(np.mean(info["audio"][0, 4800:40000] ** 2))
    assert abs(rms - 0.5 / np.sqrt(2)) < 0.03
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left


def test_error_or_interrupt_leaves_no_file(tmp_path):
    path = tmp_path / "out.mp4"
    for error in (RuntimeError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(error)), Mp4Writer(path, 64, 64) as writer:
            writer.write(np.zeros((64, 64, 3), np.uint8), np.zeros(FRAME_SAMPLES, np.float32))
            raise error
        assert list(tmp_path.iterdir()) == []


def test_background_writer_writes_the_same_file_and_raises_the_workers_error(tmp_path):
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (48, 64, 3), dtype=np.uint8) for _ in range(30)]
    audio = rng.uniform(-0.5, 0.5, (30, FRAME_SAMPLES)).astype(np.float32)
    direct, queued = tmp_path / "direct.mp4", tmp_path / "queued.mp4"
    with Mp4Writer(direct, 64, 48) as writer:
        for frame, samples in zip(frames, audio):
            writer.write(frame, samples)
    background = BackgroundMp4Writer(Mp4Writer(queued, 64, 48), max_pending=4)
    for frame, samples in zip(frames, audio):
        background.write(frame, samples)
    background.drain()
    assert background.frames_written == 30
    assert background.close() == queued
    # the same content (not the same bytes: under load libx264's threads may split the frames differently)
    expected, got = decode(direct), decode(queued)
    assert len(got["frames"]) == len(expected["frames"]) == 30 and got["audio"].shape == expected["audio"].shape
    assert np.abs(np.stack(got["frames"]).astype(np.float64) - np.stack(expected["frames"])).mean() < 2.0
    assert np.abs(got["audio"] - expected["audio"]).max() < 0.02

    failing = BackgroundMp4Writer(Mp4Writer(tmp_path / "bad.mp4", 64, 48))
    failing.write(np.zeros((10, 10, 3), np.uint8), audio[0])  # the worker raises; the caller sees it next
    with pytest.raises(Mp4Error, match="frame must be"):
        failing.drain()
    with pytest.raises(Mp4Error, match="frame must be"):
        failing.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["direct.mp4", "queued.mp4"]  # no partial file


def test_writer_rejects_bad_input(tmp_path):
    with pytest.raises(Mp4Error, match="even frame size"):
        Mp4Writer(tmp_path / "a.mp4", 63, 64)
    with Mp4Writer(tmp_path / "b.mp4", 64, 64) as writer:
        with pytest.raises(Mp4Error, match="960"):
            writer.write(np.zeros((64, 64, 3), np.uint8), np.zeros(1000, np.float32))
        writer.write(np.zeros((64, 64, 3), np.uint8), np.zeros(FRAME_SAMPLES, np.float32))


@needs_osmesa
@needs_clip
def test_render_play_on_the_beat2_clip(tmp_path):
    from render.play import main

    out = tmp_path / "clip.mp4"
    assert (
        main(
            [
                str(CLIP_NPZ),
                "--wav",
                str(CLIP_WAV),
                "--mp4",
                str(out),
                "--size",
                "128",
                "--start",
                "20",
                "--seconds",
                "2",
            ]
        )
        == 0
    )
    info = decode(out)
    check_av_sync(info, 50)
    assert np.abs(info["audio"]).max() > 0.05  # the speech is in the track
    for frame in info["frames"][::10]:
        mask = silhouette(frame, ground_rows=0.15)
        assert mask.mean() > 0.02
        cx, cy = silhouette_center(mask)
        assert abs(cx - 0.5) < 0.12 and 0.25 < cy < 0.7
    diffs = [
        np.abs(a.astype(int) - b.astype(int)).max(axis=2).mean()
        for a, b in zip(info["frames"][:-10:10], info["frames"][10::10])
    ]
    assert min(diffs) > 0.05  # the avatar moves: frames 0.4 s apart differ


def _steps(n_steps: int):
    """DialogueStep/GestureStep pairs with a tone on the agent's channel and BEAT2-like motion."""
    rng = np.random.default_rng(0)
    for step in range(n_steps):
        agent = (0.3 * np.sin(np.arange(STEP_SAMPLES) * 0.05)).astype(np.float32)
        user = (0.1 * rng.standard_normal(STEP_SAMPLES)).astype(np.float32)
        poses = np.zeros((2, 55, 3), np.float32)
        poses[:, 16, 2] = -0.3 * step
        trans = np.tile(np.float32([0.0, 1.3, 0.0]), (2, 1))
        yield (
            DialogueStep(step=step, agent_pcm=agent, user_pcm=user),
            GestureStep(
                step=step,
                poses=poses,
                trans=trans,
                expressions=np.zeros((2, 100), np.float32),
                tokens=np.zeros(20, np.int32),
            ),
        )


@needs_osmesa
def test_render_component_offline_writes_every_frame_with_the_conversation(tmp_path):
    from render.process import create_component

    out = tmp_path / "conversation.mp4"
    cfg = RenderConfig(size=96, mp4_path=str(out), encoding="jpeg")
    component = create_component(cfg, RunContext(run_dir=tmp_path, live=False, seed=0, session="t"))
    frames = []
    try:
        for dialogue, gesture in _steps(5):
            assert component.handle(dialogue) == []
            frames += component.handle(gesture)
        component.flush()
    finally:
        component.close()
    assert [f.frame_index for f in frames] == [0, 1] * 5
    assert frames[0].encoding == "jpeg" and bytes(frames[0].image[:2]) == b"\xff\xd8"
    assert component.counters()["dropped_frames"] == 0
    info = decode(out)
    check_av_sync(info, 10)
    expected = np.clip(next(_steps(1))[0].agent_pcm + next(_steps(1))[0].user_pcm, -1, 1)
    assert np.abs(info["audio"][0]).max() == pytest.approx(np.abs(expected).max(), abs=0.1)


@needs_osmesa
def test_render_component_live_drops_late_frames_and_keeps_sync(tmp_path):
    from render.process import create_component

    out = tmp_path / "live.mp4"
    cfg = RenderConfig(live_size=64, mp4_path=str(out), encoding="rgb24", max_lag_ms=2000)
    component = create_component(cfg, RunContext(run_dir=tmp_path, live=True, seed=0, session="t"))
    import time

    try:
        for dialogue, gesture in _steps(4):
            late = gesture.step % 2 == 1
            gesture.t_origin_ns = time.monotonic_ns() - (int(5e9) if late else 0)
            component.handle(dialogue)
            outputs = component.handle(gesture)
            assert len(outputs) == (0 if late else 2)
            assert all(o.image.shape == (64, 64, 3) for o in outputs)
    finally:
        component.close()
    assert component.counters()["dropped_frames"] == 4
    check_av_sync(decode(out), 8)  # dropped frames repeat the last one: the audio keeps its place


@needs_osmesa
def test_render_component_reads_capture_times_on_its_own_clock(tmp_path):
    """The capturing stage on another host: its clock 10 s behind this one. With the measured offset no frame is
    late; without it every frame would look 10 s late and be dropped."""
    import time

    from render.process import create_component

    cfg = RenderConfig(live_size=64, encoding="rgb24", max_lag_ms=2000)
    behind_ns = 10 * 10**9
    for offset_ns, expected_frames in ((behind_ns, 2), (0, 0)):
        component = create_component(cfg, RunContext(run_dir=tmp_path, live=True, seed=0, session="t"))
        component.set_origin_offset_ns(offset_ns)
        try:
            dialogue, gesture = next(_steps(1))
            gesture.t_origin_ns = time.monotonic_ns() - behind_ns
            component.handle(dialogue)
            assert len(component.handle(gesture)) == expected_frames
        finally:
            component.close()


class _RecordingWriter:
    """Stands in for Mp4Writer in the timeline tests: records what would be encoded."""

    def __init__(self):
        self.width, self.height, self.frames_written = 8, 8, 0
        self.written: list[tuple[int, float]] = []  # (frame value, first audio sample)

    def write(self, rgb, audio):
        self.written.append((int(rgb[0, 0, 0]), float(np.asarray(audio).reshape(-1)[0])))
        self.frames_written += 1


def _frame(value: int) -> np.ndarray:
    return np.full((8, 8, 3), value, np.uint8)


def _audio(step: int) -> np.ndarray:
    return np.full(STEP_SAMPLES, step / 100, np.float32)


def test_timeline_offline_waits_for_audio_and_frames_in_step_order():
    from render.process import StepTimeline

    writer = _RecordingWriter()
    timeline = StepTimeline(writer, stereo=False, live=False)
    timeline.add_frame(0, 0, _frame(10))
    timeline.add_frame(0, 1, _frame(11))
    assert writer.written == []  # no audio yet
    timeline.add_frame(1, 0, _frame(20))
    timeline.add_frame(1, 1, _frame(21))
    timeline.add_audio(1, _audio(1), np.zeros(STEP_SAMPLES, np.float32))
    assert writer.written == []  # step 0 is still incomplete: offline never skips ahead
    timeline.add_audio(0, _audio(0), np.zeros(STEP_SAMPLES, np.float32))
    assert [w[0] for w in writer.written] == [10, 11, 20, 21]
    assert [w[1] for w in writer.written] == pytest.approx([0.0, 0.0, 0.01, 0.01])
    timeline.add_audio(2, _audio(2), np.zeros(STEP_SAMPLES, np.float32))
    timeline.finish()  # end of stream: step 2 has audio but no frames -> repeats the last frame
    assert [w[0] for w in writer.written[4:]] == [21, 21] and timeline.repeated_frames == 2


def test_timeline_live_fills_a_missing_frame_once_a_later_step_is_complete():
    from render.process import StepTimeline

    writer = _RecordingWriter()
    timeline = StepTimeline(writer, stereo=True, live=True)
    timeline.add_audio(0, _audio(0), _audio(50))
    timeline.add_frame(0, 0, _frame(10))  # frame 1 of step 0 was dropped
    timeline.add_audio(1, _audio(1), _audio(51))
    timeline.add_frame(1, 0, _frame(20))
    timeline.add_frame(1, 1, _frame(21))
    assert [w[0] for w in writer.written] == [10, 10, 20, 21]
    assert writer.written[0][1] == pytest.approx(0.5)  # stereo: user on the left channel
