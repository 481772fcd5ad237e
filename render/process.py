"""The render stage: gesture.step -> two rendered frames (render.frame), and the conversation's MP4.

Each GestureStep carries two motion frames; each is posed (LBS), rendered offscreen and published as a
RenderFrame (JPEG or raw RGB). DialogueStep messages bring the step's agent and user audio for the MP4.

MP4 timeline: the audio of every dialogue step is written with the step's two frames; a frame that is
missing (dropped live, or its gesture step lost) repeats the last rendered frame, so audio and video stay in
sync to the frame. Live mode drops a frame when its step is older than `max_lag_ms` and counts it;
offline mode renders every frame and waits for both the audio and the frames of a step before writing it.

With `render.mode: browser` the page draws the avatar: this stage renders only for the MP4 (none: no GL at all)
and publishes each frame without an image (`encoding="none"`), so the run's latency stamps still reach the sink.
"""

from __future__ import annotations

import io
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ecas.core.component import RunContext, StageFailed
from ecas.core.messages import DialogueStep, GestureStep, Message, RenderFrame
from ecas.core.timing import FRAME_SAMPLES, FRAMES_PER_STEP, NS_PER_MS
from render.config import RenderConfig
from render.mp4 import BackgroundMp4Writer, Mp4WriteError, Mp4Writer, mix_conversation
from render.view import AvatarView, open_view

log = logging.getLogger(__name__)


def encode_jpeg(rgb: np.ndarray, quality: int) -> np.ndarray:
    """(H, W, 3) uint8 -> the JPEG file as a (N,) uint8 array."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(rgb).save(buffer, format="JPEG", quality=quality)
    return np.frombuffer(buffer.getvalue(), dtype=np.uint8)


class StepTimeline:
    """Pairs each step's audio with its frames and writes complete steps to the MP4 in step order.

    A step is written once its audio and both frames are in, or, live, once a later step is complete
    (its missing frames repeat the last frame, missing audio is silence). `finish` writes whatever is left.
    """

    def __init__(self, writer: Mp4Writer | BackgroundMp4Writer, stereo: bool, live: bool) -> None:
        self.writer, self.stereo, self.live = writer, stereo, live
        self.audio: dict[int, np.ndarray] = {}
        self.frames: dict[int, dict[int, np.ndarray]] = {}
        self.last_frame = np.zeros((writer.height, writer.width, 3), np.uint8)
        self.repeated_frames = 0

    def add_audio(self, step: int, agent_pcm: np.ndarray, user_pcm: np.ndarray) -> None:
        self.audio[step] = mix_conversation(agent_pcm, user_pcm, self.stereo)
        self._drain()

    def add_frame(self, step: int, index: int, rgb: np.ndarray | None) -> None:
        self.frames.setdefault(step, {})[index] = rgb
        self._drain()

    def _complete(self, step: int) -> bool:
        return step in self.audio and len(self.frames.get(step, {})) == FRAMES_PER_STEP

    def _drain(self, final: bool = False) -> None:
        while self.audio or self.frames:
            pending = sorted(set(self.audio) | set(self.frames))
            step = pending[0]
            later_complete = self.live and any(self._complete(s) for s in pending[1:])
            if not (self._complete(step) or final or later_complete):
                return
            self._write_step(step)

    def _write_step(self, step: int) -> None:
        audio = self.audio.pop(step, None)
        if audio is None:
            audio = np.zeros((FRAMES_PER_STEP * FRAME_SAMPLES,) + ((2,) if self.stereo else ()), np.float32)
        frames = self.frames.pop(step, {})
        for index in range(FRAMES_PER_STEP):
            rgb = frames.get(index)
            if rgb is None:
                rgb = self.last_frame
                self.repeated_frames += 1
            self.last_frame = rgb
            self.writer.write(rgb, audio[index * FRAME_SAMPLES : (index + 1) * FRAME_SAMPLES])

    def finish(self) -> None:
        self._drain(final=True)


class RenderComponent:
    """The render stage's component (see the module docstring)."""

    def __init__(self, cfg: RenderConfig, run: RunContext) -> None:
        self.cfg, self.live = cfg, run.live
        self.origin_offset_ns = 0  # t_origin_ns + this = capture time on this process's clock
        self.width, self.height = cfg.frame_size(run.live)
        self.rendered_frames = 0
        self.dropped_frames = 0
        self.flushed = False
        self.timeline: StepTimeline | None = None
        self.view: AvatarView | None = None
        if cfg.mode == "server" or cfg.mp4_path:
            self._open_view_and_mp4(cfg, run)

    def _open_view_and_mp4(self, cfg: RenderConfig, run: RunContext) -> None:
        self.view = open_view(cfg, self.width, self.height)
        if cfg.mp4_path:
            writer = BackgroundMp4Writer(
                Mp4Writer(
                    Path(cfg.mp4_path),
                    self.width,
                    self.height,
                    channels=2 if cfg.mp4_audio == "stereo" else 1,
                    crf=cfg.mp4_crf,
                    preset=cfg.mp4_preset,
                )
            )
            self.timeline = StepTimeline(writer, cfg.mp4_audio == "stereo", run.live)
            self.timeline_failed = False

    def counters(self) -> dict[str, int]:
        return {
            "rendered_frames": self.rendered_frames,
            "dropped_frames": self.dropped_frames,
            "mp4_frames": 0 if self.timeline is None else self.timeline.writer.frames_written,
            "mp4_repeated_frames": 0 if self.timeline is None else self.timeline.repeated_frames,
        }

    def partial_files(self) -> list[Path]:
        """The MP4 being written under its temporary name (the supervisor removes it if this process is killed)."""
        return [] if self.timeline is None else [self.timeline.writer.tmp_path]

    def handle(self, msg: Message) -> Sequence[Message]:
        try:
            if isinstance(msg, DialogueStep):
                if self.timeline is not None:
                    self.timeline.add_audio(msg.step, msg.agent_pcm, msg.user_pcm)
                return []
            if isinstance(msg, GestureStep):
                return self._render_step(msg)
            return []
        except Mp4WriteError as err:  # disk full, file too large, permission: every later frame would fail too
            self.timeline_failed = True
            raise StageFailed(str(err)) from None

    def _too_late(self, msg: GestureStep) -> bool:
        if not self.live or msg.t_origin_ns <= 0:
            return False
        lag_ns = time.monotonic_ns() - (msg.t_origin_ns + self.origin_offset_ns)
        return lag_ns > self.cfg.max_lag_ms * NS_PER_MS

    def set_origin_offset_ns(self, offset_ns: int) -> None:
        """The capturing stage's clock against this one (`ecas.core.component.ClockAware`; measured on START)."""
        self.origin_offset_ns = offset_ns

    def _render_step(self, msg: GestureStep) -> list[RenderFrame]:
        if self.cfg.mode == "browser":
            return self._browser_step(msg)
        outputs = []
        for index in range(FRAMES_PER_STEP):
            if self._too_late(msg):
                self.dropped_frames += 1
                if self.timeline is not None:
                    self.timeline.add_frame(msg.step, index, None)
                continue
            rgb = self.view.frame(msg.poses[index], msg.trans[index], msg.expressions[index])
            self.rendered_frames += 1
            if self.timeline is not None:
                self.timeline.add_frame(msg.step, index, rgb)
            image = encode_jpeg(rgb, self.cfg.jpeg_quality) if self.cfg.encoding == "jpeg" else rgb
            outputs.append(
                RenderFrame(
                    frame_index=index, width=self.width, height=self.height, encoding=self.cfg.encoding, image=image
                )
            )
        return outputs

    def _browser_step(self, msg: GestureStep) -> list[RenderFrame]:
        """The page draws the avatar: frames for the MP4 only, and image-less frames for the latency stamps."""
        outputs = []
        for index in range(FRAMES_PER_STEP):
            if self.timeline is not None:
                if self._too_late(msg):
                    self.dropped_frames += 1
                    self.timeline.add_frame(msg.step, index, None)
                else:
                    rgb = self.view.frame(msg.poses[index], msg.trans[index], msg.expressions[index])
                    self.rendered_frames += 1
                    self.timeline.add_frame(msg.step, index, rgb)
            outputs.append(RenderFrame(frame_index=index, encoding="none", image=np.zeros(0, np.uint8)))
        return outputs

    def flush(self) -> Sequence[Message]:
        """End of stream: write what is left and finalise the MP4 now, so a failure to write it fails the run
        (the stage's end of stream is only sent after this)."""
        if self.timeline is not None:
            try:
                self.timeline.finish()
                self.timeline.writer.close(commit=True)
            except Mp4WriteError as err:
                self.timeline_failed = True
                raise StageFailed(str(err)) from None
        self.flushed = True
        return []

    def close(self) -> None:
        """Finalise the MP4 and release GL.

        The MP4 is renamed into place after the end of the stream, and also in live mode when the session is
        stopped (Ctrl-C ends a live conversation; what was recorded is a complete, playable file). An offline
        run stopped before its end leaves no file: its temporary file is deleted.
        """
        try:
            if self.timeline is not None:
                commit = (self.flushed or self.live) and not self.timeline_failed
                if commit:
                    self.timeline.finish()
                path = self.timeline.writer.close(commit=commit)
                log.info("mp4 %s (%d frames)", path or "discarded", self.timeline.writer.frames_written)
        finally:
            if self.view is not None:
                self.view.close()


def create_component(cfg: RenderConfig, run: RunContext) -> RenderComponent:
    return RenderComponent(cfg, run)
