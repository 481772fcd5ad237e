"""A pipecat sink that writes the avatar's frames and the speech to an MP4, and the offset measured back from it.

`Mp4Sink` pairs each `OutputImageRawFrame` with the audio frames that follow it (the avatar service pushes a frame's
image, then its 40 ms of speech; an idle frame has no audio and gets silence), exactly `FRAME_SAMPLES` per frame.
`speech_offset_ms` decodes the written file and finds where the speech sits in its audio track (cross-correlation
with the speech that went in) and where the first speaking video frame sits in its video track.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pipecat.frames.frames import EndFrame, Frame, OutputAudioRawFrame, OutputImageRawFrame
from pipecat.processors.frame_processor import FrameDirection, FrameProcessor

from ecas.core.timing import FRAME_SAMPLES, MOTION_FPS, SAMPLE_RATE_HZ
from ecas.pipecat.audio import pcm16_to_mono
from render.mp4 import BackgroundMp4Writer, Mp4Writer

VOICED_RMS = 0.02  # a 1 s piece of speech this loud (-34 dBFS) is found unambiguously by cross-correlation
MATCH_GAIN = (0.8, 1.25)  # the correlation peak over the piece's energy: near 1 where the file holds the piece


class Mp4Sink(FrameProcessor):
    """The last processor of a pipeline: every image with its audio into `path` (written on EndFrame)."""

    def __init__(self, path: str | Path, width: int, height: int, **kwargs) -> None:
        super().__init__(**kwargs)
        self.path = Path(path)
        self._writer = BackgroundMp4Writer(Mp4Writer(self.path, width, height))
        self._image: np.ndarray | None = None
        self._audio: list[np.ndarray] = []
        self.frames = 0
        self.first_speech_frame: int | None = None
        self.missing_frames = 0  # gaps in the service's frame numbers
        self.audio_samples = 0
        self._last_index: int | None = None

    async def process_frame(self, frame: Frame, direction: FrameDirection) -> None:
        await super().process_frame(frame, direction)
        if isinstance(frame, OutputImageRawFrame):
            self._write_pending()
            self._image = np.frombuffer(frame.image, np.uint8).reshape(frame.size[1], frame.size[0], 3)
            self._check_index(frame)
        elif isinstance(frame, OutputAudioRawFrame):
            if frame.sample_rate != SAMPLE_RATE_HZ:
                raise ValueError(f"Mp4Sink: audio must be {SAMPLE_RATE_HZ} Hz, got {frame.sample_rate}")
            self._audio.append(pcm16_to_mono(frame.audio, frame.num_channels))
        elif isinstance(frame, EndFrame):
            self._write_pending()
            self._writer.close(commit=True)
        await self.push_frame(frame, direction)

    def _check_index(self, frame: OutputImageRawFrame) -> None:
        index = frame.metadata.get("avatar_frame")
        if index is not None and self._last_index is not None:
            self.missing_frames += max(0, index - self._last_index - 1)
        self._last_index = index
        if frame.metadata.get("avatar_speech") and self.first_speech_frame is None:
            self.first_speech_frame = self.frames

    def _write_pending(self) -> None:
        if self._image is None:
            return
        audio = np.concatenate(self._audio) if self._audio else np.zeros(0, np.float32)
        self.audio_samples += audio.size
        slot = np.zeros(FRAME_SAMPLES, np.float32)
        slot[: min(audio.size, FRAME_SAMPLES)] = audio[:FRAME_SAMPLES]
        self._writer.write(self._image, slot)
        self.frames += 1
        self._image, self._audio = None, []


def decode_mp4(path: str | Path) -> tuple[np.ndarray, np.ndarray, float]:
    """(video frame times s (F,), audio (N,) float32 mono at its rate, audio rate) of an MP4, as a player reads it."""
    import av

    with av.open(str(path)) as container:
        video = [f.time for f in container.decode(video=0)]
    with av.open(str(path)) as container:
        stream = container.streams.audio[0]
        rate = stream.rate
        chunks = [f.to_ndarray().mean(axis=0) for f in container.decode(audio=0)]  # (C, n) -> (n,)
        start = float(stream.start_time * stream.time_base) if stream.start_time is not None else 0.0
    audio = np.concatenate(chunks).astype(np.float32)
    if start > 0:  # the audio track starts late: pad so sample 0 is time 0
        audio = np.concatenate([np.zeros(int(round(start * rate)), np.float32), audio])
    elif start < 0:  # priming samples before time 0 (AAC encoder delay) are not played
        audio = audio[int(round(-start * rate)) :]
    return np.asarray(video, np.float64), audio, float(rate)


def speech_offset_ms(path: str | Path, speech: np.ndarray, first_speech_frame: int, probes: int = 5) -> float:
    """Audio-to-video offset of the speech in the written file, ms (positive: the sound comes after its picture);
    the largest in magnitude of `probes` places spread over the speech, so a drift shows too.

    At each place a 1 s piece of the speech (24 kHz) is found in the decoded audio track by cross-correlation within
    ±1 s of where it belongs; its picture is where the same sample sits on the video track, counted from the frame
    the service marked as the first speaking frame, at its decoded time."""
    from scipy.signal import correlate

    video_times, audio, rate = decode_mp4(path)
    if rate != SAMPLE_RATE_HZ:
        raise ValueError(f"{path}: audio at {rate} Hz, expected {SAMPLE_RATE_HZ}")
    if first_speech_frame >= len(video_times):
        raise ValueError(f"{path}: has no frame {first_speech_frame}")
    picture0_s = float(video_times[first_speech_frame])
    piece, search = SAMPLE_RATE_HZ, SAMPLE_RATE_HZ
    offsets = []
    for at in _voiced_places(speech, piece, probes):
        probe = speech[at : at + piece]
        picture_s = picture0_s + at / SAMPLE_RATE_HZ
        lo = max(0, int(round(picture_s * rate)) - search)
        window = audio[lo : lo + piece + 2 * search]
        if window.size < piece:
            continue
        lags = correlate(window, probe, mode="valid", method="fft")  # (window - piece + 1,)
        best = int(np.argmax(lags))
        if MATCH_GAIN[0] < lags[best] / float(np.dot(probe, probe)) < MATCH_GAIN[1]:  # the piece itself, not noise
            offsets.append(1000.0 * ((lo + best) / rate - picture_s))
    return max(offsets, key=abs) if offsets else float("nan")


def _voiced_places(speech: np.ndarray, piece: int, count: int) -> list[int]:
    """`count` starts of pieces spread over the speech, each loud enough to be found (silence matches anything)."""
    starts = np.arange(0, max(1, speech.size - piece + 1), piece // 2)
    loud = [int(a) for a in starts if np.sqrt(np.mean(np.square(speech[a : a + piece]))) >= VOICED_RMS]
    if not loud:
        return []
    return [loud[i] for i in np.linspace(0, len(loud) - 1, min(count, len(loud))).round().astype(int)]


def video_seconds(frames: int) -> float:
    return frames / MOTION_FPS
