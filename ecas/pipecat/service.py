"""`AvatarService`: our avatar in a pipecat pipeline, in the place of its hosted video avatar services.

    pipeline = Pipeline([transport.input(), stt, user_agg, llm, tts, AvatarService(), transport.output(), bot_agg])

It takes the bot's speech (`TTSAudioRawFrame`, any size and rate), the words the TTS reports (`TTSTextFrame`) and
the user's audio (`InputAudioRawFrame`, for listening behaviour), drives the engine 80 ms at a time and emits, for
every 40 ms video frame, an `OutputImageRawFrame` (the server renderer, `sync_with_audio` so the transport shows it
as its audio starts) followed by the frame's speech (the same audio, re-cut to 40 ms), and once per step an
`AvatarMotionFrame` (SMPL-X parameters, for a browser avatar). Between utterances it keeps the avatar alive on the
wall clock (listening, idle) with video only. Every other frame leaves in order with the speech around it.

Lifecycle: the engine and the renderer load on `StartFrame`, each in its own thread (the renderer's GL context
belongs to its thread); `EndFrame` finishes the waiting speech first; `CancelFrame` stops at once. An
`InterruptionFrame` (the user barges in) drops the speech still waiting here and any step in flight, as pipecat's
own services drop their queues; the transport drops what it had queued.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pipecat.frames.frames import (
    CancelFrame,
    DataFrame,
    EndFrame,
    Frame,
    InputAudioRawFrame,
    InterruptionFrame,
    OutputAudioRawFrame,
    OutputImageRawFrame,
    StartFrame,
    SystemFrame,
    TTSAudioRawFrame,
    TTSStartedFrame,
    TTSStoppedFrame,
    TTSTextFrame,
)
from pipecat.processors.frame_processor import FrameDirection, FrameProcessor

from ecas.core.timing import FRAME_SAMPLES, FRAMES_PER_STEP, SAMPLE_RATE_HZ, STEP_S, STEP_SAMPLES
from ecas.pipecat.audio import ToEngineRate, mono_to_pcm16, pcm16_to_mono
from ecas.pipecat.timeline import Marker, SpeechBuffer, StepAudio, UserAudio
from render.config import RenderConfig

MAX_IDLE_LAG_STEPS = 3  # an idle timeline this far behind the wall clock skips ahead instead of catching up
SECONDS_PER_CHAR = 0.065  # a word's duration when the TTS gives only its start


@dataclass
class AvatarMotionFrame(DataFrame):
    """The avatar's motion of one 80 ms step (a `gesture.engine.MotionStep`), for a client that draws it."""

    motion: Any


@dataclass
class AvatarStats:
    """What the service did; `latency_ms` holds the newest `window` latencies (speech frame in -> image out)."""

    window: int = 100_000
    speech_frames: int = 0
    idle_frames: int = 0
    interrupted_steps: int = 0
    skipped_idle_steps: int = 0
    dropped_frames: int = 0  # speech frames later than `render.max_lag_ms`: the last image is shown again
    latency_ms: deque = field(default_factory=deque)
    engine_ms: deque = field(default_factory=deque)  # one engine step
    render_ms: deque = field(default_factory=deque)  # one frame

    def __post_init__(self) -> None:
        self.latency_ms, self.engine_ms, self.render_ms = (deque(maxlen=self.window) for _ in range(3))

    def percentile_ms(self, q: float, of: str = "latency_ms") -> float | None:
        values = getattr(self, of)
        return float(np.percentile(np.asarray(values), q)) if values else None


@dataclass
class _Plan:
    """One engine step to run: the speech of the step (None: an idle step) and the generation it belongs to."""

    generation: int
    speech: StepAudio | None
    user_pcm: np.ndarray
    words: tuple
    due_s: float  # monotonic time at which the step is shown, if the transport plays what it is given in real time


class AvatarService(FrameProcessor):
    """See the module docstring. `engine`: a ready `gesture.engine.Engine` (else one is built from `config`,
    `overrides` and `seed` at start); `render`: the server renderer's options, or None for motion only (a browser
    draws the avatar); `idle_video`: keep emitting frames between utterances; `stall_s`: how long a half-filled
    step waits for more speech before it is padded with silence."""

    def __init__(
        self,
        *,
        engine: Any = None,
        config: Any = None,
        overrides: tuple[str, ...] = (),
        seed: int = 0,
        render: RenderConfig | None = RenderConfig(),
        motion_frames: bool = True,
        idle_video: bool = True,
        stall_s: float = 0.5,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        if stall_s <= 0:
            raise ValueError(f"stall_s: must be > 0, got {stall_s}")
        self._engine, self._engine_args = engine, (config, tuple(overrides), seed)
        self._owns_engine = engine is None  # a given engine is reset at start and left open at the end
        self._render_cfg, self._motion_frames, self._idle_video, self._stall_s = (
            render,
            motion_frames,
            idle_video,
            stall_s,
        )
        self.width, self.height = render.frame_size(live=True) if render is not None else (0, 0)
        self.stats = AvatarStats()
        self._view = None
        self._engine_pool: ThreadPoolExecutor | None = None
        self._render_pool: ThreadPoolExecutor | None = None
        self._reset_state()

    def _reset_state(self) -> None:
        self._speech, self._user = SpeechBuffer(), UserAudio()
        self._speech_rate, self._user_rate = ToEngineRate(), ToEngineRate()
        self._words: list = []
        self._generation = 0
        self._in_utterance = self._utterance_ended = self._ending = False
        self._last_speech_s = 0.0
        self._anchor_s = time.monotonic()
        self._steps_out = 0
        self._frames_out = 0
        self._last_image: np.ndarray | None = None
        self._in_flight = 0  # speech steps between the buffer and their frames leaving
        self._utterance_start = (0, 0)  # (sample position, pipeline clock ns) of the utterance's first audio
        self._audio_cls: type[OutputAudioRawFrame] = TTSAudioRawFrame
        self._context_id: str | None = None
        self._wake = asyncio.Event()
        self._plans: deque[_Plan] = deque()  # run by the engine, waiting for their motion
        self._video_queue: asyncio.Queue = asyncio.Queue()
        self._ended = asyncio.Event()
        self._motion_task = self._video_task = None

    # -- pipecat entry point --------------------------------------------------------------------------------------

    async def process_frame(self, frame: Frame, direction: FrameDirection) -> None:
        await super().process_frame(frame, direction)
        if isinstance(frame, StartFrame):
            await self._start()
            await self.push_frame(frame, direction)
        elif isinstance(frame, CancelFrame):
            await self._stop()
            await self.push_frame(frame, direction)
        elif isinstance(frame, EndFrame):
            await self._finish()
            await self.push_frame(frame, direction)
        elif isinstance(frame, InterruptionFrame):
            await self._interrupt()
            await self.push_frame(frame, direction)
        elif direction == FrameDirection.UPSTREAM:
            await self.push_frame(frame, direction)
        elif isinstance(frame, OutputAudioRawFrame):
            self._add_speech(frame)
        elif isinstance(frame, InputAudioRawFrame):
            self._user.push(self._user_rate(pcm16_to_mono(frame.audio, frame.num_channels), frame.sample_rate))
            await self.push_frame(frame, direction)
        elif isinstance(frame, SystemFrame):
            await self.push_frame(frame, direction)
        else:
            await self._in_order(frame)

    # -- input ----------------------------------------------------------------------------------------------------

    def _add_speech(self, frame: OutputAudioRawFrame) -> None:
        now_ns = time.monotonic_ns()
        if not self._in_utterance:
            self._in_utterance, self._utterance_ended = True, False
            self._utterance_start = (self._speech.end_samples, self.get_clock().get_time())
        self._audio_cls, self._context_id = type(frame), getattr(frame, "context_id", None)
        pcm = self._speech_rate(pcm16_to_mono(frame.audio, frame.num_channels), frame.sample_rate)
        self._speech.push(pcm, now_ns)
        self._last_speech_s = now_ns / 1e9
        self._wake.set()

    async def _in_order(self, frame: Frame) -> None:
        """A data or control frame: it leaves after the speech that arrived before it."""
        if isinstance(frame, TTSTextFrame):
            self._words.append(self._word(frame))
        if isinstance(frame, TTSStoppedFrame) and self._in_utterance:
            self._speech.push(self._speech_rate.flush(), time.monotonic_ns())
            self._utterance_ended = True
        if isinstance(frame, TTSStartedFrame):
            self._speech_rate.flush()
        if self._speech.waiting_samples == 0 and self._in_flight == 0 and not self._speech.has_markers:
            await self.push_frame(frame)
        else:
            self._speech.mark(frame)
        self._wake.set()

    def _word(self, frame: TTSTextFrame):
        """The word on the engine's clock: from its pts relative to the utterance's first audio when the TTS gives
        timestamps, else where it arrives in the speech; its end is estimated from its length."""
        from gesture.engine import Word

        start_samples, start_clock_ns = self._utterance_start
        if frame.pts and self._in_utterance:
            start_s = start_samples / SAMPLE_RATE_HZ + max(0, frame.pts - start_clock_ns) / 1e9
        else:
            start_s = self._speech.end_samples / SAMPLE_RATE_HZ
        return Word(frame.text, start_s, start_s + max(0.1, SECONDS_PER_CHAR * len(frame.text)))

    # -- lifecycle ------------------------------------------------------------------------------------------------

    async def _start(self) -> None:
        loop = asyncio.get_running_loop()
        self._engine_pool = ThreadPoolExecutor(1, thread_name_prefix="avatar-engine")
        await loop.run_in_executor(self._engine_pool, self._open_engine)
        if self._render_cfg is not None:
            self._render_pool = ThreadPoolExecutor(1, thread_name_prefix="avatar-render")
            await loop.run_in_executor(self._render_pool, self._open_view)
        self._reset_state()
        self._motion_task = self.create_task(self._motion_loop(), "avatar-motion")
        self._video_task = self.create_task(self._video_loop(), "avatar-video")

    def _open_engine(self) -> None:
        import torch

        torch.set_num_threads(1)
        if self._engine is None:
            from gesture.engine import Engine

            config, overrides, seed = self._engine_args
            self._engine = Engine.from_config(config=config, overrides=overrides, seed=seed)
        else:
            self._engine.reset()

    def _open_view(self) -> None:
        from render.view import open_view

        self._view = open_view(self._render_cfg, self.width, self.height)

    async def _finish(self) -> None:
        """End of stream: every waiting step leaves (the last padded), then its markers, then the engine closes."""
        if self._motion_task is not None:
            self._ending = True
            self._wake.set()
            await self._ended.wait()  # set by the video loop after the last step's frames
            for marker in self._speech.drop():
                await self.push_frame(marker.item)
        await self._stop()

    async def _stop(self) -> None:
        for task in (self._motion_task, self._video_task):
            if task is not None:
                await self.cancel_task(task)
        self._motion_task = self._video_task = None
        loop = asyncio.get_running_loop()
        if self._engine_pool is not None:
            await loop.run_in_executor(self._engine_pool, self._close_engine)
            self._engine_pool.shutdown()
            self._engine_pool = None
        if self._render_pool is not None:
            await loop.run_in_executor(self._render_pool, self._close_view)
            self._render_pool.shutdown()
            self._render_pool = None

    def _close_engine(self) -> None:
        if self._owns_engine and self._engine is not None:
            self._engine.close()
            self._engine = None

    def _close_view(self) -> None:
        if self._view is not None:
            self._view.close()
            self._view = None

    async def _interrupt(self) -> None:
        """The user barged in: the waiting speech, the steps in flight and their frames are dropped."""
        self._generation += 1
        self.stats.interrupted_steps += len(self._plans) + self._video_queue.qsize()
        for marker in self._speech.drop():
            if not marker.item.interruptible:
                await self.push_frame(marker.item)
        self._speech_rate.flush()
        self._words.clear()
        self._plans.clear()
        self._in_flight = 0
        self._in_utterance = self._utterance_ended = False
        self._anchor_s = time.monotonic() - self._steps_out * STEP_S  # the timeline restarts now
        self._wake.set()

    # -- the motion loop: what to run next, and the engine --------------------------------------------------------

    async def _motion_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            plan = await self._next_plan()
            if plan is None:  # end of stream: the engine's last steps, then the end mark for the video loop
                for motion in await loop.run_in_executor(self._engine_pool, self._engine_flush):
                    await self._pair(motion)
                await self._video_queue.put(self._ended)
                return
            self._plans.append(plan)
            motions = await loop.run_in_executor(self._engine_pool, self._engine_step, plan)
            if plan.generation != self._generation:
                continue  # interrupted while the engine ran
            for motion in motions:
                await self._pair(motion)

    async def _next_plan(self) -> _Plan | None:
        while True:
            self._wake.clear()
            plan = self._speech_plan() or self._idle_plan()
            if plan is not None or (self._ending and self._speech.waiting_samples == 0):
                return plan
            try:
                await asyncio.wait_for(self._wake.wait(), self._wait_s())
            except TimeoutError:
                if self._in_utterance and time.monotonic() - self._last_speech_s >= self._stall_s:
                    self._utterance_ended = True  # the TTS went quiet: pad what is there, then idle

    def _speech_plan(self) -> _Plan | None:
        step = self._speech.take(pad=self._ending or self._utterance_ended)
        if self._speech.waiting_samples == 0 and (self._utterance_ended or self._ending):
            self._in_utterance = self._utterance_ended = False
        if step is None:
            return None
        self._anchor_s = max(self._anchor_s, time.monotonic() - self._steps_out * STEP_S)
        self._in_flight += 1
        return self._plan(step)

    def _idle_plan(self) -> _Plan | None:
        """An idle step once its 80 ms have passed on the wall clock (and no speech is under way)."""
        if not self._idle_video or self._in_utterance or self._ending:
            return None
        late_s = time.monotonic() - (self._anchor_s + (self._steps_out + 1) * STEP_S)
        if late_s < 0:
            return None
        if late_s > MAX_IDLE_LAG_STEPS * STEP_S:  # the machine fell behind: skip ahead rather than catch up
            skipped = int(late_s / STEP_S)
            self.stats.skipped_idle_steps += skipped
            self._anchor_s += skipped * STEP_S
        return self._plan(None)

    def _plan(self, speech: StepAudio | None) -> _Plan:
        words, self._words = tuple(self._words), []
        due_s = self._anchor_s + self._steps_out * STEP_S
        self._steps_out += 1
        return _Plan(self._generation, speech, self._user.take(), words, due_s)

    def _wait_s(self) -> float | None:
        if self._in_utterance:
            return max(0.0, self._last_speech_s + self._stall_s - time.monotonic())
        if self._idle_video and not self._ending:
            return max(0.0, self._anchor_s + (self._steps_out + 1) * STEP_S - time.monotonic())
        return None

    def _engine_step(self, plan: _Plan) -> list:
        agent = plan.speech.pcm if plan.speech is not None else np.zeros(STEP_SAMPLES, np.float32)
        t0 = time.perf_counter()
        motion = self._engine.step(agent, user_pcm=plan.user_pcm, words=plan.words)
        self.stats.engine_ms.append(1000 * (time.perf_counter() - t0))
        return _as_list(motion)

    def _engine_flush(self) -> list:
        return _as_list(self._engine.flush()) if hasattr(self._engine, "flush") else []

    async def _pair(self, motion) -> None:
        """The engine's motion of its oldest planned step goes to the renderer with that step's speech."""
        if not self._plans:
            return  # the plan was dropped by an interruption
        plan = self._plans.popleft()
        await self._video_queue.put((plan, motion))

    # -- the video loop: render, then push the step's frames ------------------------------------------------------

    async def _video_loop(self) -> None:
        while True:
            item = await self._video_queue.get()
            if isinstance(item, asyncio.Event):
                item.set()
                continue
            plan, motion = item
            if plan.generation == self._generation:
                await self._push_step(plan, motion)

    async def _push_step(self, plan: _Plan, motion) -> None:
        """The step's motion, then per frame: the markers before it, its image, its speech; then the markers after."""
        speech = plan.speech
        if self._motion_frames:
            await self.push_frame(AvatarMotionFrame(motion=motion))
        for index in range(FRAMES_PER_STEP):
            if speech is not None:
                await self._push_markers(speech.markers, speech.start_samples + index * FRAME_SAMPLES)
            if self._render_pool is not None:
                arrival_ns = speech.arrival_ns[index] if speech is not None else None
                if not await self._push_image(plan, motion, index, arrival_ns):
                    return  # interrupted while rendering
            if speech is None:
                self.stats.idle_frames += 1
                continue
            await self.push_frame(self._speech_frame(speech.frame_pcm(index)))
            self.stats.speech_frames += 1
        if speech is None:
            return
        await self._push_markers(speech.markers, speech.end_samples)
        self._in_flight -= 1
        if self._in_flight == 0 and self._speech.waiting_samples == 0:
            for marker in self._speech.take_markers():
                await self.push_frame(marker.item)

    async def _push_image(self, plan: _Plan, motion, index: int, arrival_ns: int | None) -> bool:
        """Render frame `index` of the step and push it; a speech frame already `max_lag_ms` past the time it is shown
        repeats the last image instead (counted as dropped). False when an interruption came during the render."""
        due_s = plan.due_s + index * STEP_S / FRAMES_PER_STEP
        late = arrival_ns is not None and time.monotonic() - due_s > self._render_cfg.max_lag_ms / 1000
        if late and self._last_image is not None:
            self.stats.dropped_frames += 1
            rgb = self._last_image
        else:
            loop = asyncio.get_running_loop()
            rgb = await loop.run_in_executor(self._render_pool, self._render, motion, index)
            if plan.generation != self._generation:
                return False
        image = OutputImageRawFrame(image=rgb.tobytes(), size=(self.width, self.height), format="RGB")
        image.sync_with_audio = True
        image.metadata.update(avatar_frame=self._frames_out, avatar_speech=plan.speech is not None, avatar_late=late)
        self._frames_out += 1
        self._last_image = rgb
        await self.push_frame(image)
        if arrival_ns is not None:
            self.stats.latency_ms.append((time.monotonic_ns() - arrival_ns) / 1e6)
        return True

    def _render(self, motion, index: int) -> np.ndarray:
        t0 = time.perf_counter()
        rgb = self._view.frame(
            np.asarray(motion.poses[index]), np.asarray(motion.trans[index]), motion.expressions[index]
        )
        self.stats.render_ms.append(1000 * (time.perf_counter() - t0))
        return rgb

    def _speech_frame(self, pcm: np.ndarray) -> OutputAudioRawFrame:
        audio = self._audio_cls(mono_to_pcm16(pcm), SAMPLE_RATE_HZ, 1)
        if isinstance(audio, TTSAudioRawFrame):
            audio.context_id = self._context_id
        return audio

    async def _push_markers(self, markers: list[Marker], until_samples: int) -> None:
        while markers and markers[0].pos_samples <= until_samples:
            await self.push_frame(markers.pop(0).item)


def _as_list(motion) -> list:
    if motion is None:
        return []
    return list(motion) if isinstance(motion, (list, tuple)) else [motion]
