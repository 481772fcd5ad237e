"""Streaming pocketsphinx recognition at 16 kHz with a per-step work budget.

Audio queued by `feed` is decoded at most `budget_samples` per `advance` call, so a pre-roll or the
tail of an utterance is spread over a few steps instead of landing on one.
"""

import re
from dataclasses import dataclass

import numpy as np

from dialogue.vad import VAD_RATE_HZ

FRAME_RATE_HZ = 100  # pocketsphinx segment times are in 10 ms frames
_ALT_PRON = re.compile(r"\(\d+\)$")
_FILLERS = {"<s>", "</s>", "<sil>", "[noise]", "[speech]", "[laugh]", "[breath]", "[cough]", "[um]", "[uh]"}


@dataclass(frozen=True)
class RecognizedWord:
    word: str
    start_s: float  # stream time
    end_s: float


def clean_word(word: str) -> str | None:
    word = _ALT_PRON.sub("", word)
    return None if word.lower() in _FILLERS or word.startswith("[") else word


class StreamingAsr:
    """One utterance at a time: `begin(t_s)`, `feed(pcm)`, `advance()` each step, `finish()`, then poll `final`."""

    def __init__(
        self,
        hmm: str | None = None,
        lm: str | None = None,
        dict_path: str | None = None,
        budget_samples: int = 1920,
        max_hmm_per_frame: int = 2000,
        max_words_per_frame: int = 8,
        phone_lookahead_frames: int = 5,
    ):
        from pocketsphinx import Decoder

        kwargs = {k: v for k, v in dict(hmm=hmm, lm=lm, dict=dict_path).items() if v is not None}
        # fwdflat off: its second pass costs ~200 ms at end of utterance and did not help accuracy here.
        self._decoder = Decoder(
            samprate=VAD_RATE_HZ,
            loglevel="FATAL",
            fwdflat=False,
            maxhmmpf=max_hmm_per_frame,
            maxwpf=max_words_per_frame,
            pl_window=phone_lookahead_frames,
            **kwargs,
        )
        self.budget_samples = budget_samples
        self.reset()

    def reset(self) -> None:
        if getattr(self, "active", False):
            self._decoder.end_utt()
        self.active = False  # an utterance is open
        self._finishing = False
        self._backlog: list[np.ndarray] = []
        self._t0_s = 0.0
        self.partial = ""

    def begin(self, t_s: float, preroll: np.ndarray) -> None:
        """Open an utterance whose first sample (the start of `preroll`) is at stream time t_s."""
        if self.active:
            self._decoder.end_utt()
        self._decoder.start_utt()
        self.active, self._finishing, self._t0_s, self.partial = True, False, t_s, ""
        self._backlog = [np.asarray(preroll, np.float32)]

    def feed(self, pcm16k: np.ndarray) -> None:
        if self.active and not self._finishing:
            self._backlog.append(np.asarray(pcm16k, np.float32))

    def finish(self) -> None:
        """No more audio for this utterance; the final hypothesis comes once the backlog is decoded."""
        self._finishing = self.active

    def advance(self) -> list[RecognizedWord] | None:
        """Decode up to the budget; returns the final words when a finished utterance completes, else None."""
        if not self.active:
            return None
        pending = np.concatenate(self._backlog) if self._backlog else np.zeros(0, np.float32)
        now, rest = pending[: self.budget_samples], pending[self.budget_samples :]
        self._backlog = [rest] if rest.size else []
        if now.size:
            pcm16 = (np.clip(now, -1.0, 1.0) * 32767).astype(np.int16)
            self._decoder.process_raw(pcm16.tobytes(), False, False)
            hyp = self._decoder.hyp()
            self.partial = " ".join(w for w in (clean_word(x) for x in (hyp.hypstr.split() if hyp else [])) if w)
        if self._finishing and not self._backlog:
            return self._final_words()
        return None

    def _final_words(self) -> list[RecognizedWord]:
        self._decoder.end_utt()
        self.active, self._finishing, self.partial = False, False, ""
        words = []
        for seg in self._decoder.seg():
            word = clean_word(seg.word)
            if word:
                words.append(
                    RecognizedWord(
                        word,
                        self._t0_s + seg.start_frame / FRAME_RATE_HZ,
                        self._t0_s + (seg.end_frame + 1) / FRAME_RATE_HZ,
                    )
                )
        return words
