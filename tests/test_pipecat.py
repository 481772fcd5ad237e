"""The avatar service in real pipecat pipelines (pipecat's own `run_test`), with the real engine and renderer.

Skipped where pipecat is not installed (the `pipecat` extra). Each test feeds the service as a TTS would and checks
what leaves it: every speech sample, in order, after its picture; the frames that must keep their place in the
speech; nothing of an utterance after the user barges in.
"""

from __future__ import annotations

import asyncio
import os
import time

import numpy as np
import pytest

pipecat = pytest.importorskip("pipecat")

from pipecat.frames.frames import (  # noqa: E402
    InterruptionFrame,
    OutputAudioRawFrame,
    OutputImageRawFrame,
    TTSAudioRawFrame,
    TTSStartedFrame,
    TTSStoppedFrame,
    TTSTextFrame,
)
from pipecat.pipeline.pipeline import Pipeline  # noqa: E402
from pipecat.processors.frame_processor import FrameProcessor  # noqa: E402
from pipecat.tests.utils import SleepFrame, run_test  # noqa: E402

from ecas.core.timing import FRAME_SAMPLES, SAMPLE_RATE_HZ, STEP_SAMPLES  # noqa: E402
from ecas.pipecat import AvatarMotionFrame, AvatarService  # noqa: E402
from ecas.pipecat.audio import mono_to_pcm16, pcm16_to_mono  # noqa: E402
from render.config import RenderConfig  # noqa: E402

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
SMALL = RenderConfig(live_size=64)


@pytest.fixture(scope="module")
def engine():
    from gesture.engine import Engine

    eng = Engine.from_config()
    yield eng
    eng.close()


def speech(seconds: float, seed: int = 0) -> np.ndarray:
    """A voiced test signal (a vowel-like buzz with a moving pitch) at 24 kHz, int16-exact floats."""
    t = np.arange(int(seconds * SAMPLE_RATE_HZ)) / SAMPLE_RATE_HZ
    f0 = 120 + 20 * np.sin(2 * np.pi * 0.7 * t + seed)
    pcm = 0.3 * np.sign(np.sin(2 * np.pi * np.cumsum(f0) / SAMPLE_RATE_HZ)) * (0.6 + 0.4 * np.sin(2 * np.pi * 3 * t))
    return np.round(pcm * 32768) / 32768


def tts_frames(pcm: np.ndarray, chunk_sizes=(480, 2000, 777, 4800, 31)) -> list[TTSAudioRawFrame]:
    """The speech cut as a TTS stream cuts it: varying sizes, not multiples of a frame."""
    out, pos, i = [], 0, 0
    while pos < pcm.size:
        n = chunk_sizes[i % len(chunk_sizes)]
        out.append(TTSAudioRawFrame(mono_to_pcm16(pcm[pos : pos + n]), SAMPLE_RATE_HZ, 1, context_id="c1"))
        pos, i = pos + n, i + 1
    return out


def speech_out(frames) -> np.ndarray:
    audio = [pcm16_to_mono(f.audio, f.num_channels) for f in frames if isinstance(f, OutputAudioRawFrame)]
    return np.concatenate(audio) if audio else np.zeros(0, np.float32)


def images(frames) -> list[OutputImageRawFrame]:
    return [f for f in frames if isinstance(f, OutputImageRawFrame)]


def check_pictures_lead_their_speech(frames) -> None:
    """Each speech audio frame (40 ms) follows the image of its frame; speech images are each followed by one."""
    last = None
    for f in frames:
        if isinstance(f, OutputAudioRawFrame):
            assert isinstance(last, OutputImageRawFrame) and last.metadata["avatar_speech"]
            assert f.num_frames == FRAME_SAMPLES
        if isinstance(f, (OutputAudioRawFrame, OutputImageRawFrame)):
            if isinstance(last, OutputImageRawFrame) and last.metadata["avatar_speech"]:
                assert isinstance(f, OutputAudioRawFrame), "a speech image without its audio"
            last = f


START_DEADLINE_S = 120.0  # the engine and the GL renderer start on StartFrame; run_test's default is 1 s


def run(service, frames, **kwargs):
    down, _ = asyncio.run(run_test(service, frames_to_send=frames, start_timeout=START_DEADLINE_S, **kwargs))
    return down


def test_end_of_stream_sends_every_sample_in_order_then_the_stop(engine):
    pcm = speech(1.03)
    service = AvatarService(engine=engine, render=SMALL, idle_video=False)
    down = run(service, [TTSStartedFrame(), *tts_frames(pcm), TTSStoppedFrame()])

    out = speech_out(down)
    steps = -(-pcm.size // STEP_SAMPLES)
    assert out.size == steps * STEP_SAMPLES  # the last step padded with silence
    np.testing.assert_array_equal(out[: pcm.size], pcm.astype(np.float32))
    assert not out[pcm.size :].any()
    kinds = [type(f) for f in down if not isinstance(f, (AvatarMotionFrame, OutputImageRawFrame))]
    assert kinds[0] is TTSStartedFrame and kinds[-1] is TTSStoppedFrame
    assert len(images(down)) == 2 * steps == service.stats.speech_frames
    assert sum(isinstance(f, AvatarMotionFrame) for f in down) == steps
    assert [f.metadata["avatar_frame"] for f in images(down)] == list(range(2 * steps))
    check_pictures_lead_their_speech(down)
    assert all(f.size == (64, 64) and len(f.image) == 64 * 64 * 3 for f in images(down))
    assert len(service.stats.latency_ms) == 2 * steps


def test_text_frames_keep_their_place_in_the_speech(engine):
    """A word that arrives after 0.5 s of speech leaves after that speech and before the speech after it."""
    first, second = speech(0.5), speech(0.5, seed=1)
    word = TTSTextFrame("hello", text_type="word")
    service = AvatarService(engine=engine, render=None, idle_video=False)
    down = run(service, [TTSStartedFrame(), *tts_frames(first), word, *tts_frames(second), TTSStoppedFrame()])

    at = next(i for i, f in enumerate(down) if isinstance(f, TTSTextFrame))
    before = speech_out(down[:at])
    assert first.size <= before.size < first.size + FRAME_SAMPLES  # the frame holding the word's first sample
    assert speech_out(down).size >= first.size + second.size
    assert not images(down)  # render=None: motion only
    assert sum(isinstance(f, AvatarMotionFrame) for f in down) == -(-(first.size + second.size) // STEP_SAMPLES)


class BargeIn(FrameProcessor):
    """Before the avatar: pushes an InterruptionFrame once the avatar's first speech has left (`heard` is set)."""

    def __init__(self, heard: asyncio.Event) -> None:
        super().__init__()
        self.heard = heard
        self.task = None

    async def process_frame(self, frame, direction):
        await super().process_frame(frame, direction)
        if isinstance(frame, TTSStartedFrame):
            self.task = self.create_task(self._barge())
        await self.push_frame(frame, direction)

    async def _barge(self):
        await self.heard.wait()
        await self.push_frame(InterruptionFrame())


class Ear(FrameProcessor):
    """After the avatar: sets `heard` on the first speech audio."""

    def __init__(self, heard: asyncio.Event) -> None:
        super().__init__()
        self.heard = heard

    async def process_frame(self, frame, direction):
        await super().process_frame(frame, direction)
        if isinstance(frame, OutputAudioRawFrame):
            self.heard.set()
        await self.push_frame(frame, direction)


def test_interruption_mid_utterance_drops_the_rest(engine):
    pcm = speech(4.0)
    service = AvatarService(engine=engine, render=SMALL, idle_video=False)

    async def go():
        heard = asyncio.Event()
        pipeline = Pipeline([BargeIn(heard), service, Ear(heard)])
        frames = [TTSStartedFrame(), *tts_frames(pcm), TTSStoppedFrame()]
        down, _ = await run_test(pipeline, frames_to_send=frames, start_timeout=START_DEADLINE_S)
        return down

    down = asyncio.run(go())
    cut = next(i for i, f in enumerate(down) if isinstance(f, InterruptionFrame))
    spoken = speech_out(down[:cut])
    assert 0 < spoken.size < pcm.size  # it was speaking, and did not finish
    np.testing.assert_array_equal(spoken, pcm[: spoken.size].astype(np.float32))
    after = down[cut + 1 :]
    assert not speech_out(after).size  # nothing of the utterance after the barge-in
    assert not any(isinstance(f, TTSStoppedFrame) for f in after)  # its queued frames are dropped too
    assert service.stats.speech_frames * FRAME_SAMPLES >= spoken.size


def test_audio_faster_than_real_time_loses_nothing(engine):
    """3 s of speech at once: every sample and frame leaves, with no idle frame slipped in. (The lag limit is off:
    on a loaded 2-core machine the steps can take longer than real time, and a live service would then drop.)"""
    pcm = speech(3.0)
    no_lag_limit = RenderConfig(live_size=64, max_lag_ms=3_600_000)
    service = AvatarService(engine=engine, render=no_lag_limit, idle_video=True)
    t0 = time.monotonic()
    down = run(service, [TTSStartedFrame(), TTSAudioRawFrame(mono_to_pcm16(pcm), SAMPLE_RATE_HZ, 1), TTSStoppedFrame()])
    elapsed_s = time.monotonic() - t0

    out = speech_out(down)
    np.testing.assert_array_equal(out[: pcm.size], pcm.astype(np.float32))
    assert service.stats.dropped_frames == 0
    assert service.stats.speech_frames == 2 * -(-pcm.size // STEP_SAMPLES)
    # the speech played from its start ends after the run, so no idle frame was slipped in between its frames
    speech_images = [f.metadata["avatar_speech"] for f in images(down)]
    first = speech_images.index(True)
    assert all(speech_images[first : first + service.stats.speech_frames])
    assert elapsed_s > 0


def test_long_silence_keeps_the_avatar_alive_and_a_stalled_step_leaves(engine):
    """Between utterances, idle frames on the wall clock; a TTS that goes quiet mid-step has its partial step padded
    and shown after `stall_s`, before the rest of the utterance arrives."""
    first, second = speech(0.12), speech(0.2, seed=2)  # 0.12 s = 1.5 steps
    service = AvatarService(engine=engine, render=SMALL, idle_video=True, stall_s=0.3)
    t0 = time.monotonic()
    down = run(
        service, [TTSStartedFrame(), *tts_frames(first), SleepFrame(1.2), *tts_frames(second), TTSStoppedFrame()]
    )
    elapsed_s = time.monotonic() - t0

    speech_flags = [f.metadata["avatar_speech"] for f in images(down)]
    runs = np.flatnonzero(np.diff(np.asarray(speech_flags, int)) != 0)
    assert len(runs) >= 2, "idle frames between the two parts of the utterance"
    out = speech_out(down)
    assert out.size == 2 * STEP_SAMPLES + (-(-second.size // STEP_SAMPLES)) * STEP_SAMPLES
    np.testing.assert_array_equal(out[: first.size], first.astype(np.float32))
    idle = service.stats.idle_frames + 2 * service.stats.skipped_idle_steps
    assert idle >= 4  # alive in the silence (a loaded machine makes fewer than the 18 the wall clock allows)
    assert idle <= 25 * elapsed_s + 2  # never more frames than the wall clock allows


def test_bad_options_are_named():
    with pytest.raises(ValueError, match="stall_s"):
        AvatarService(render=None, stall_s=0)
