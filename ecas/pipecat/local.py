"""The project's own speech recognition, voice and rule-based responder as pipecat services, for a bot that runs
with nothing hosted: `LocalSTTService` (pocketsphinx, on VAD segments), `LocalTTSService` (espeak-ng) and
`RuleResponderService` (in the place of an LLM service when no OpenAI-compatible endpoint is given).
"""

from __future__ import annotations

import asyncio

from pipecat.frames.frames import (
    LLMContextFrame,
    LLMFullResponseEndFrame,
    LLMFullResponseStartFrame,
    LLMTextFrame,
    TranscriptionFrame,
    TTSAudioRawFrame,
)
from pipecat.processors.frame_processor import FrameDirection, FrameProcessor
from pipecat.services.settings import STTSettings, TTSSettings
from pipecat.services.stt_service import SegmentedSTTService
from pipecat.services.tts_service import TTSService
from pipecat.utils.time import time_now_iso8601

from ecas.core.timing import FRAME_SAMPLES, SAMPLE_RATE_HZ
from ecas.pipecat.audio import mono_to_pcm16

ASR_RATE_HZ = 16_000  # pocketsphinx's en-us model
TTS_CHUNK_SAMPLES = 4 * FRAME_SAMPLES  # the voice is streamed in 160 ms chunks, as a streaming TTS would


class LocalSTTService(SegmentedSTTService):
    """pocketsphinx on each VAD segment (the pipeline needs a `VADProcessor` before it)."""

    def __init__(self, **kwargs) -> None:
        super().__init__(sample_rate=ASR_RATE_HZ, settings=STTSettings(model=None, language=None), **kwargs)
        from pocketsphinx import Decoder

        self._decoder = Decoder(samprate=ASR_RATE_HZ, loglevel="FATAL")

    @property
    def wants_wav_segments(self) -> bool:
        return False  # raw int16 at 16 kHz, which pocketsphinx reads

    def can_generate_metrics(self) -> bool:
        return False

    def _decode(self, audio: bytes) -> str:
        from dialogue.asr import clean_word

        self._decoder.start_utt()
        self._decoder.process_raw(audio, full_utt=True)
        self._decoder.end_utt()
        words = [clean_word(seg.word) for seg in self._decoder.seg()]
        return " ".join(w for w in words if w)

    async def run_stt(self, audio: bytes):
        text = await asyncio.to_thread(self._decode, audio)
        if text:
            yield TranscriptionFrame(text, self._user_id, time_now_iso8601())


class LocalTTSService(TTSService):
    """espeak-ng through the project's `dialogue.tts.EspeakTts`, at 24 kHz."""

    def __init__(self, *, voice: str = "en-us", rate_wpm: int = 175, **kwargs) -> None:
        super().__init__(
            sample_rate=SAMPLE_RATE_HZ,
            push_start_frame=True,
            push_stop_frames=True,
            settings=TTSSettings(model=None, voice=voice, language=None),
            **kwargs,
        )
        from dialogue.tts import EspeakTts

        self._tts = EspeakTts(voice=voice, rate_wpm=rate_wpm)

    def can_generate_metrics(self) -> bool:
        return False

    async def run_tts(self, text: str, context_id: str):
        utterance = await asyncio.to_thread(self._tts.synthesize, text)
        pcm = utterance.pcm
        for start in range(0, pcm.size, TTS_CHUNK_SAMPLES):
            chunk = mono_to_pcm16(pcm[start : start + TTS_CHUNK_SAMPLES])
            yield TTSAudioRawFrame(chunk, SAMPLE_RATE_HZ, 1, context_id=context_id)


class RuleResponderService(FrameProcessor):
    """The project's rule-based responder where an LLM service would be: it answers the context's last user message
    with one LLM response (start, text, end), which the TTS service speaks."""

    def __init__(self, seed: int = 0, **kwargs) -> None:
        super().__init__(**kwargs)
        from dialogue.responder import RuleResponder

        self._responder = RuleResponder(seed=seed)

    async def process_frame(self, frame, direction: FrameDirection) -> None:
        await super().process_frame(frame, direction)
        if not isinstance(frame, LLMContextFrame):
            await self.push_frame(frame, direction)
            return
        users = [m for m in frame.context.get_messages() if isinstance(m, dict) and m.get("role") == "user"]
        text = _message_text(users[-1]) if users else ""
        await self.push_frame(LLMFullResponseStartFrame())
        await self.push_frame(LLMTextFrame(self._responder.respond(text)))
        await self.push_frame(LLMFullResponseEndFrame())


def _message_text(message: dict) -> str:
    content = message.get("content", "")
    if isinstance(content, list):  # content parts
        return " ".join(part.get("text", "") for part in content if isinstance(part, dict))
    return str(content)
