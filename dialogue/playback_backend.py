"""The agent speaks a given recording (`--speak FILE`), for co-speech gesture on real speech.

Its text tokens come from the transcript when one is given (whisper json, TextGrid, or plain text
force-aligned), else from recognising the recording; alignment runs once at start-up. The user is still
heard (VAD, ASR for the transcript, speech codes); the recording plays on regardless (no barge-in).
"""

from pathlib import Path

import numpy as np

from dialogue.alignment import recognize, words_from_transcript
from dialogue.config import DialogueConfig
from dialogue.listener import STEP_S, ListeningBackend, UserListener
from dialogue.local_backend import check_user_pcm, load_speech_tokenizer, step_message, user_turn_from
from dialogue.speaker import Speaker
from dialogue.speech_tokenizer import SpeechTokenizer, StreamingSpeechEncoder
from dialogue.text_vocab import LOCAL_SPEC
from dialogue.transcript import Transcript
from dialogue.tts import Utterance, WordTiming
from ecas.core.audio_file import load_audio
from ecas.core.messages import DialogueStep
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES


def recording_utterance(path: str, transcript: str | None) -> Utterance:
    pcm = load_audio(path, SAMPLE_RATE_HZ)
    if transcript:
        words = words_from_transcript(Path(transcript), pcm, SAMPLE_RATE_HZ)
    else:
        words = recognize(pcm, SAMPLE_RATE_HZ)
    timings = tuple(
        WordTiming(w.word, int(round(w.start_s * SAMPLE_RATE_HZ)))
        for w in words
        if 0 <= w.start_s * SAMPLE_RATE_HZ < len(pcm)
    )
    return Utterance(text=" ".join(w.word for w in words), pcm=pcm, words=timings)


class PlaybackBackend(ListeningBackend):
    spec = LOCAL_SPEC

    def __init__(self, utterance: Utterance, listener: UserListener, tokenizer: SpeechTokenizer, start_s: float = 0.0):
        self.utterance, self.listener, self.start_s = utterance, listener, start_s
        self.transcript = Transcript("playback")
        self.speaker = Speaker(self.transcript)
        self.agent_codes = StreamingSpeechEncoder(tokenizer)
        self.user_codes = StreamingSpeechEncoder(tokenizer)
        self.reset()

    @classmethod
    def from_config(cls, cfg: DialogueConfig, seed: int = 0) -> "PlaybackBackend":
        p = cfg.playback
        backend = cls(
            recording_utterance(p.speak, p.transcript),
            UserListener(cfg.vad, cfg.echo, cfg.asr),
            load_speech_tokenizer(cfg.speech_tokenizer),
            p.start_s,
        )
        backend.step(np.zeros(STEP_SAMPLES, np.float32))  # warm-up: the first calls of each model are slow
        backend.reset()
        return backend

    def reset(self) -> None:
        for part in (self.listener, self.speaker, self.agent_codes, self.user_codes):
            part.reset()
        self.transcript.turns.clear()
        self._step_index = 0
        self._started = False
        self._last_agent_pcm: np.ndarray | None = None

    def close(self) -> None:
        pass

    def step(self, user_pcm: np.ndarray) -> DialogueStep:
        user_pcm = check_user_pcm(user_pcm)
        t_s = self._step_index * STEP_S
        if not self._started and t_s >= self.start_s - 1e-9:
            self.speaker.play(self.utterance)
            self._started = True
        heard = self.listener.step(user_pcm, self._last_agent_pcm)
        if heard.final_words is not None:
            user_turn_from(heard, self.transcript).answered = None
        spoken = self.speaker.step(t_s)
        self._last_agent_pcm = spoken.pcm
        self._step_index += 1
        user_words = " ".join(w.word for w in heard.final_words or [])
        return step_message(user_pcm, heard, spoken, self.agent_codes, self.user_codes, user_words)
