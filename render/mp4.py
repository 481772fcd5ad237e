"""MP4 writer: H.264 yuv420p video and AAC audio with exactly one video frame's worth of audio per frame.

The file is written under a temporary name next to the target and renamed on a successful `close()`;
`close(commit=False)`, an exception inside `with Mp4Writer(...)` or Ctrl-C removes it, so a partial MP4
is never left behind by the writer; a process killed while writing leaves `tmp_path`, which its supervisor
removes (the render stage reports it). A write that fails (disk full, file too large, permission) raises
`Mp4WriteError`, one line naming the target and the OS error.
"""

from __future__ import annotations

import os
import queue
import threading
from fractions import Fraction
from pathlib import Path

import av
import numpy as np

from ecas.core.timing import MOTION_FPS, SAMPLE_RATE_HZ


class Mp4Error(RuntimeError):
    """Bad input to the MP4 writer."""


class Mp4WriteError(Mp4Error):
    """The file cannot be written; no later frame will fare better."""

    def __init__(self, path: Path, err: OSError):
        super().__init__(
            f"cannot write {path} ([Errno {err.errno}] {err.strerror or err})"
            if err.errno
            else f"cannot write {path} ({err})"
        )


class Mp4Writer:
    """Write (H, W, 3) uint8 frames, each with its `samples_per_frame` audio samples (mono or stereo float32)."""

    def __init__(
        self,
        path: str | Path,
        width: int,
        height: int,
        fps: int = MOTION_FPS,
        sample_rate_hz: int = SAMPLE_RATE_HZ,
        channels: int = 1,
        crf: int = 20,
        preset: str = "veryfast",
    ) -> None:
        if width % 2 or height % 2:
            raise Mp4Error(f"yuv420p needs an even frame size, got {width}x{height}")
        if sample_rate_hz % fps:
            raise Mp4Error(f"{sample_rate_hz} Hz audio does not divide into {fps} frames per second")
        if channels not in (1, 2):
            raise Mp4Error(f"audio channels must be 1 (mixed) or 2 (stereo), got {channels}")
        self.path = Path(path)
        self.width, self.height, self.fps = width, height, fps
        self.sample_rate_hz, self.channels = sample_rate_hz, channels
        self.samples_per_frame = sample_rate_hz // fps
        self.frames_written = 0
        self.tmp_path = self.path.with_name(f".{self.path.name}.{os.getpid()}.partial")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._container = av.open(str(self.tmp_path), mode="w", format="mp4")
        except OSError as err:
            raise Mp4WriteError(self.path, err) from None
        self._video = self._container.add_stream("libx264", rate=fps)
        self._video.width, self._video.height, self._video.pix_fmt = width, height, "yuv420p"
        self._video.options = {"crf": str(crf), "preset": preset}
        self._video.codec_context.time_base = Fraction(1, fps)
        self._audio = self._container.add_stream("aac", rate=sample_rate_hz)
        self._audio.layout = "mono" if channels == 1 else "stereo"
        self._closed = False

    def write(self, frame_rgb: np.ndarray, audio: np.ndarray) -> None:
        """frame_rgb (H, W, 3) uint8; audio (samples_per_frame,) or (samples_per_frame, channels) float32."""
        if frame_rgb.shape != (self.height, self.width, 3) or frame_rgb.dtype != np.uint8:
            raise Mp4Error(
                f"frame must be ({self.height}, {self.width}, 3) uint8, got {frame_rgb.shape} {frame_rgb.dtype}"
            )
        audio = np.asarray(audio, dtype=np.float32)
        if audio.ndim == 1:
            audio = audio[:, None]
        if audio.shape[0] != self.samples_per_frame or audio.shape[1] not in (1, self.channels):
            raise Mp4Error(
                f"audio must be ({self.samples_per_frame},) or ({self.samples_per_frame}, {self.channels}) "
                f"per frame, got {audio.shape}"
            )
        planar = np.ascontiguousarray(np.broadcast_to(audio, (self.samples_per_frame, self.channels)).T)  # (C, N)
        video_frame = av.VideoFrame.from_ndarray(frame_rgb, format="rgb24")
        video_frame.pts = self.frames_written
        audio_frame = av.AudioFrame.from_ndarray(
            np.clip(planar, -1.0, 1.0), format="fltp", layout=self._audio.layout.name
        )
        audio_frame.sample_rate = self.sample_rate_hz
        audio_frame.pts = self.frames_written * self.samples_per_frame
        try:
            self._container.mux(self._video.encode(video_frame))
            self._container.mux(self._audio.encode(audio_frame))
        except OSError as err:
            raise Mp4WriteError(self.path, err) from None
        self.frames_written += 1

    def close(self, commit: bool = True) -> Path | None:
        """Flush and finalise; rename to the target on commit, otherwise delete the partial file."""
        if self._closed:
            return self.path if commit else None
        self._closed = True
        if not commit:
            self._discard()
            return None
        try:
            self._container.mux(self._video.encode(None))
            self._container.mux(self._audio.encode(None))
            self._container.close()
        except OSError as err:
            self.tmp_path.unlink(missing_ok=True)
            raise Mp4WriteError(self.path, err) from None
        except BaseException:
            self.tmp_path.unlink(missing_ok=True)
            raise
        os.replace(self.tmp_path, self.path)
        return self.path

    def _discard(self) -> None:
        try:
            self._container.close()
        except OSError:
            pass  # the file is deleted anyway; a write error was already reported
        finally:
            self.tmp_path.unlink(missing_ok=True)

    def __enter__(self) -> Mp4Writer:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(commit=exc_type is None)


class BackgroundMp4Writer:
    """An Mp4Writer fed by a worker thread, so H.264 encoding overlaps the caller's rendering (libx264 and the GL
    readback both run without the GIL) and stays off the step's latency. `write` queues a frame (blocking only
    when `max_pending` frames wait); frames are written in order. The first error of the worker is raised by the
    next `write`, `drain` or `close`; frames queued after it are discarded."""

    _STOP = object()

    def __init__(self, writer: Mp4Writer, max_pending: int = 50) -> None:
        self.writer = writer
        self.width, self.height, self.tmp_path = writer.width, writer.height, writer.tmp_path
        self._queue: queue.Queue = queue.Queue(maxsize=max_pending)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="mp4-writer", daemon=True)
        self._thread.start()

    @property
    def frames_written(self) -> int:
        return self.writer.frames_written

    def _run(self) -> None:
        while (item := self._queue.get()) is not self._STOP:
            try:
                if self._error is None:
                    self.writer.write(*item)
            except BaseException as err:  # kept for the caller's thread
                self._error = err
            finally:
                self._queue.task_done()
        self._queue.task_done()

    def _raise_error(self) -> None:
        if self._error is not None:
            raise self._error

    def write(self, frame_rgb: np.ndarray, audio: np.ndarray) -> None:
        self._raise_error()
        self._queue.put((frame_rgb, audio))

    def drain(self) -> None:
        """Wait until every queued frame is written."""
        self._queue.join()
        self._raise_error()

    def close(self, commit: bool = True) -> Path | None:
        """Write what is queued (on commit), stop the worker and close the file as `Mp4Writer.close` does."""
        if self._thread.is_alive():
            self._queue.put(self._STOP)
            self._thread.join()
        if self._error is not None:
            self.writer.close(commit=False)
            raise self._error
        return self.writer.close(commit=commit)


def mix_conversation(agent_pcm: np.ndarray, user_pcm: np.ndarray, stereo: bool) -> np.ndarray:
    """The MP4 audio of a step: user and agent mixed (N,) or stereo (N, 2) with the user left, agent right."""
    agent = np.asarray(agent_pcm, dtype=np.float32)
    user = np.asarray(user_pcm, dtype=np.float32)
    if stereo:
        return np.stack([user, agent], axis=1)
    return np.clip(user + agent, -1.0, 1.0)
