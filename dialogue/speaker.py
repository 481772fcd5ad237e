"""The agent's voice: queued utterances played 1920 samples a step, a text token at each word's first step.

Sentences are synthesised lazily, at most one per step and only when less than two steps of audio remain,
so synthesis cost is spread over the reply. Every reply becomes an agent turn of the transcript, with the
time each word started; a barge-in cuts the reply at the current step and marks the word being spoken.
"""

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dialogue.text_vocab import word_token
from dialogue.transcript import Transcript, Turn, Word
from dialogue.tts import Utterance
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES

FADE_SAMPLES = SAMPLE_RATE_HZ // 200  # 5 ms fade-out when cut
SILENCE_LEVEL = 1e-3


@dataclass
class SpokenStep:
    pcm: np.ndarray  # (1920,) float32
    text_token: int
    text_piece: str
    speaking: bool
    interrupted: bool = False
    first_audio: bool = False  # this step carries the first audio of a reply


class Speaker:
    def __init__(
        self,
        transcript: Transcript,
        synthesize: Callable[[str], Utterance] | None = None,
        token_of: Callable[[str], int] = word_token,
    ):
        self.transcript = transcript
        self._synthesize = synthesize
        self._token_of = token_of
        self.reset()

    def reset(self) -> None:
        self._buf = np.zeros(0, np.float32)  # the current reply's audio not yet played
        self._word_starts: deque[tuple[int, str]] = deque()  # (sample in _buf, word)
        self._texts: deque[str] = deque()  # sentences not yet synthesised
        self._pieces: deque[str] = deque()  # words started but not yet given a token step
        self._turn: Turn | None = None
        self._reply_open = False  # more text may still arrive for the current reply
        self._speech_end = 0  # in _buf: end of the last non-silent sample
        self._reply_text: list[str] = []

    @property
    def busy(self) -> bool:
        """A reply is in progress (audio to play, text to synthesise, or more text coming)."""
        return self._reply_open or bool(self._texts) or self._buf.size > 0

    def begin_reply(self) -> None:
        self._reply_open = True

    def say(self, text: str) -> None:
        """Queue a sentence of the current reply."""
        if text.strip():
            self._texts.append(text.strip())
            self._add_reply_text(text.strip())

    def end_reply(self) -> None:
        """No more text for this reply."""
        self._reply_open = False

    def play(self, utterance: Utterance) -> None:
        """Queue ready-made audio with its word timings (playback backend)."""
        self._append(utterance)
        self._add_reply_text(utterance.text)

    def step(self, t_s: float) -> SpokenStep:
        """One step of agent audio starting at stream time t_s."""
        if self._buf.size < 2 * STEP_SAMPLES and self._texts and self._synthesize is not None:
            self._append(self._synthesize(self._texts.popleft()))
        chunk = np.zeros(STEP_SAMPLES, np.float32)
        n = min(STEP_SAMPLES, self._buf.size)
        chunk[:n] = self._buf[:n]
        first_audio = False
        if n and self._turn is None:
            self._turn = self.transcript.add(Turn("agent", start_s=t_s, end_s=t_s, text=" ".join(self._reply_text)))
            first_audio = True
        while self._word_starts and self._word_starts[0][0] < STEP_SAMPLES:
            offset, word = self._word_starts.popleft()
            self._close_last_word(t_s + offset / SAMPLE_RATE_HZ)
            self._turn.words.append(Word(word, t_s + offset / SAMPLE_RATE_HZ, t_s + offset / SAMPLE_RATE_HZ))
            self._pieces.append(word)
        if self._turn is not None and self._speech_end > 0:
            self._turn.end_s = t_s + min(n, self._speech_end) / SAMPLE_RATE_HZ
        self._consume(n)
        piece = self._pieces.popleft() if self._pieces else ""
        speaking = n > 0
        if self._turn is not None and not self.busy:
            self._finish_turn()
        return SpokenStep(chunk, self._token_of(piece) if piece else -1, piece, speaking, first_audio=first_audio)

    def cut(self, t_s: float) -> SpokenStep:
        """Barge-in: stop at the start of this step (a 5 ms fade of what would have played), drop the reply.

        The agent turn is marked interrupted at the last word that had started; returns the step to play.
        """
        pcm = np.zeros(STEP_SAMPLES, np.float32)
        n = min(FADE_SAMPLES, self._buf.size)
        pcm[:n] = self._buf[:n] * np.linspace(1.0, 0.0, FADE_SAMPLES, dtype=np.float32)[:n]
        had_turn = self._turn is not None
        if had_turn:
            self._turn.interrupted = True
            self._turn.interrupted_at_word = len(self._turn.words) - 1 if self._turn.words else None
            self._close_last_word(t_s)
            self._turn.end_s = t_s
        self.reset()
        return SpokenStep(pcm, -1, "", speaking=False, interrupted=had_turn)

    def _add_reply_text(self, text: str) -> None:
        self._reply_text.append(text)
        if self._turn is not None:
            self._turn.text = " ".join(self._reply_text)

    def _append(self, utterance: Utterance) -> None:
        base = self._buf.size
        loud = np.flatnonzero(np.abs(utterance.pcm) > SILENCE_LEVEL)
        if loud.size:
            self._speech_end = base + int(loud[-1]) + 1
        self._buf = np.concatenate([self._buf, utterance.pcm.astype(np.float32)])
        self._word_starts.extend((base + w.start_sample, w.word) for w in utterance.words)

    def _consume(self, n: int) -> None:
        self._buf = self._buf[n:]
        self._speech_end -= n
        self._word_starts = deque((s - n, w) for s, w in self._word_starts)

    def _close_last_word(self, t_s: float) -> None:
        if self._turn is not None and self._turn.words:
            self._turn.words[-1].end_s = max(self._turn.words[-1].start_s, t_s)

    def _finish_turn(self) -> None:
        self._close_last_word(self._turn.end_s)
        self._turn = None
        self._reply_text = []
