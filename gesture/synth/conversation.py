"""A dyadic conversation: two espeak-ng voices taking turns, with gaps, overlaps, backchannels and barge-ins.

The agent and the user each get their own audio channel. Every word carries its speaker, start and end
(the end is where the voice stops before the next word), whether it is stressed (a content word), and the
time of its energy peak (its vowel nucleus), where the agent's beat strokes land.

Turn-taking: a speaker says 1..n sentences; the next turn starts after a gap drawn from a clipped normal
(negative gaps overlap). In the partner's pauses the listener may backchannel ("mm-hmm"). With some
probability the user barges into an agent turn: the agent stops mid-word a reaction time later.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from math import gcd

import numpy as np
from scipy.signal import resample_poly

from dialogue.tts import EspeakTts
from ecas.core.timing import SAMPLE_RATE_HZ as TTS_SAMPLE_RATE_HZ
from gesture.synth.config import SynthConfig
from gesture.synth.sentences import SentenceGenerator

AGENT, USER = "agent", "user"
ENVELOPE_HOP_S = 0.01
VOICED_FRACTION = 0.05  # of the utterance's envelope peak
FADE_S = 0.02  # fade-out where the agent is cut off
MIN_PAUSE_S = 0.25  # a gap between words this long is a pause (backchannel opportunity)
STROKE_SEARCH_S = 0.35  # the energy peak of a word is looked for in its first 350 ms

STOPWORDS = frozenset(
    [
        "a",
        "an",
        "the",
        "and",
        "or",
        "but",
        "so",
        "to",
        "of",
        "in",
        "on",
        "at",
        "for",
        "with",
        "from",
        "by",
        "is",
        "are",
        "was",
        "were",
        "be",
        "been",
        "am",
        "i",
        "you",
        "he",
        "she",
        "it",
        "we",
        "they",
        "me",
        "my",
        "your",
        "our",
        "his",
        "her",
        "its",
        "their",
        "this",
        "that",
        "there",
        "these",
        "those",
        "do",
        "did",
        "does",
        "have",
        "has",
        "had",
        "not",
        "no",
        "yes",
        "oh",
        "um",
        "uh",
        "would",
        "should",
        "could",
        "will",
        "can",
        "just",
        "about",
        "as",
        "if",
        "then",
        "than",
        "what",
        "when",
        "why",
        "how",
        "who",
        "which",
        "all",
        "some",
        "any",
        "one",
        "well",
        "really",
        "mean",
        "know",
        "mm-hmm",
        "mm",
        "uh-huh",
        "okay",
    ]
)


@dataclass(frozen=True)
class SpokenWord:
    word: str
    speaker: str
    start_s: float
    end_s: float
    peak_s: float  # the word's energy peak (stroke target)
    stressed: bool


@dataclass(frozen=True)
class Turn:
    speaker: str
    start_s: float
    end_s: float
    kind: str  # "turn" or "backchannel"
    interrupted: bool
    sentence_spans_s: tuple[tuple[float, float], ...]


@dataclass(frozen=True)
class Conversation:
    duration_s: float
    sample_rate_hz: int
    channels: dict[str, np.ndarray]  # speaker -> (N,) float32
    words: tuple[SpokenWord, ...]  # both speakers, by start time
    turns: tuple[Turn, ...]  # both speakers, by start time

    def words_of(self, speaker: str) -> tuple[SpokenWord, ...]:
        return tuple(w for w in self.words if w.speaker == speaker)

    def turns_of(self, speaker: str, kind: str | None = None) -> tuple[Turn, ...]:
        return tuple(t for t in self.turns if t.speaker == speaker and (kind is None or t.kind == kind))

    @property
    def mix(self) -> np.ndarray:
        return np.clip(self.channels[AGENT] + self.channels[USER], -1.0, 1.0)


@dataclass
class _Piece:
    """One placed utterance group (a turn or a backchannel) before mixing."""

    speaker: str
    start_s: float
    pcm: np.ndarray  # (N,) at the output rate
    words: list[SpokenWord]  # times relative to the piece start
    kind: str
    sentence_spans_s: list[tuple[float, float]]
    interrupted: bool = False

    @property
    def duration_s(self) -> float:
        return self.words[-1].end_s if self.words else 0.0

    def pauses_s(self) -> list[float]:
        """Relative times where this piece pauses (a gap >= MIN_PAUSE_S after a word)."""
        return [a.end_s for a, b in zip(self.words, self.words[1:]) if b.start_s - a.end_s >= MIN_PAUSE_S]


def is_stressed(word: str) -> bool:
    core = re.sub(r"[^a-z'-]", "", word.lower())
    return len(core) >= 3 and core not in STOPWORDS


def envelope(pcm: np.ndarray, sample_rate_hz: int, hop_s: float = ENVELOPE_HOP_S) -> np.ndarray:
    """RMS per hop: (N,) -> (ceil(N / hop),)."""
    hop = max(1, int(round(sample_rate_hz * hop_s)))
    n = -(-len(pcm) // hop)
    padded = np.zeros(n * hop, np.float64)
    padded[: len(pcm)] = pcm
    return np.sqrt((padded.reshape(n, hop) ** 2).mean(1))  # (n,)


class _Speaker:
    """One voice: synthesises sentences at the output rate with timed, stress-marked words."""

    def __init__(self, name: str, voice: str, rate_wpm: int, pitch: int, sample_rate_hz: int):
        self.name, self.sample_rate_hz = name, sample_rate_hz
        self.tts = EspeakTts(voice=voice, rate_wpm=rate_wpm, pitch=pitch)
        g = gcd(TTS_SAMPLE_RATE_HZ, sample_rate_hz)
        self._up, self._down = sample_rate_hz // g, TTS_SAMPLE_RATE_HZ // g

    def say(self, text: str) -> tuple[np.ndarray, list[SpokenWord]]:
        utt = self.tts.synthesize(text)
        pcm = resample_poly(utt.pcm, self._up, self._down).astype(np.float32)  # (N,) at the output rate
        env = envelope(pcm, self.sample_rate_hz)
        voiced = env > VOICED_FRACTION * max(env.max(), 1e-9)
        starts = [w.start_sample / TTS_SAMPLE_RATE_HZ for w in utt.words] + [len(pcm) / self.sample_rate_hz]
        words = []
        for i, w in enumerate(utt.words):
            a, b = (
                int(starts[i] / ENVELOPE_HOP_S),
                max(int(starts[i + 1] / ENVELOPE_HOP_S), int(starts[i] / ENVELOPE_HOP_S) + 1),
            )
            active = np.flatnonzero(voiced[a:b])
            end_s = float(a + active[-1] + 1) * ENVELOPE_HOP_S if len(active) else starts[i] + 0.05
            search = env[a : min(b, a + int(STROKE_SEARCH_S / ENVELOPE_HOP_S))]
            peak_s = float(a + int(np.argmax(search))) * ENVELOPE_HOP_S if len(search) else starts[i]
            words.append(
                SpokenWord(w.word, self.name, starts[i], max(end_s, starts[i] + 0.03), peak_s, is_stressed(w.word))
            )
        return pcm, words


def _shift(words: list[SpokenWord], dt: float) -> list[SpokenWord]:
    return [SpokenWord(w.word, w.speaker, w.start_s + dt, w.end_s + dt, w.peak_s + dt, w.stressed) for w in words]


class ConversationBuilder:
    """Builds one seeded session; all randomness comes from ``rng``."""

    def __init__(self, cfg: SynthConfig, rng: np.random.Generator):
        self.cfg, self.rng = cfg, rng
        self.sentences = SentenceGenerator(rng)
        self.speakers = {
            AGENT: self._voice(AGENT, cfg.agent_voices),
            USER: self._voice(USER, cfg.user_voices),
        }

    def _voice(self, name: str, voices: tuple[str, ...]) -> _Speaker:
        voice = voices[int(self.rng.integers(len(voices)))]
        rate = int(self.rng.integers(self.cfg.rate_wpm[0], self.cfg.rate_wpm[1] + 1))
        pitch = int(self.rng.integers(self.cfg.pitch[0], self.cfg.pitch[1] + 1))
        return _Speaker(name, voice, rate, pitch, self.cfg.audio_sample_rate_hz)

    def _turn(self, speaker: str, start_s: float) -> _Piece:
        lo, hi = self.cfg.sentences_per_turn
        sr = self.cfg.audio_sample_rate_hz
        pcms, words, spans, t = [], [], [], 0.0
        for k in range(int(self.rng.integers(lo, hi + 1))):
            if k:
                pause = np.zeros(int(self.rng.uniform(*self.cfg.sentence_pause_s) * sr), np.float32)
                pcms.append(pause)
                t += len(pause) / sr
            pcm, sentence_words = self.speakers[speaker].say(self.sentences.sentence())
            words += _shift(sentence_words, t)
            spans.append((t + sentence_words[0].start_s, t + sentence_words[-1].end_s))
            pcms.append(pcm)
            t += len(pcm) / sr
        return _Piece(speaker, start_s, np.concatenate(pcms), words, "turn", spans)

    def _backchannel(self, speaker: str, start_s: float) -> _Piece:
        pcm, words = self.speakers[speaker].say(self.sentences.backchannel())
        words = [SpokenWord(w.word, w.speaker, w.start_s, w.end_s, w.peak_s, False) for w in words]
        return _Piece(
            speaker, start_s - words[0].start_s, pcm, words, "backchannel", [(words[0].start_s, words[-1].end_s)]
        )

    def _interrupt(self, piece: _Piece) -> float | None:
        """Maybe cut an agent turn where the user barges in; returns the user's onset (absolute) or None."""
        dur = piece.duration_s
        if piece.speaker != AGENT or dur < 2.0 or self.rng.random() >= self.cfg.interruption_prob:
            return None
        onset = self.rng.uniform(1.0, dur - 0.5)
        cut = onset + self.rng.uniform(*self.cfg.reaction_s)
        if cut >= dur - 0.1:
            return None
        sr = self.cfg.audio_sample_rate_hz
        n_cut, n_fade = int(cut * sr), int(FADE_S * sr)
        pcm = piece.pcm[:n_cut].copy()
        pcm[-n_fade:] *= np.linspace(1.0, 0.0, n_fade, dtype=np.float32)
        kept = [w for w in piece.words if w.start_s < cut - 0.02]
        last = kept[-1]
        kept[-1] = SpokenWord(
            last.word, last.speaker, last.start_s, min(last.end_s, cut), min(last.peak_s, cut), last.stressed
        )
        piece.pcm, piece.words, piece.interrupted = pcm, kept, True
        piece.sentence_spans_s = [(a, min(b, cut)) for a, b in piece.sentence_spans_s if a < cut]
        return piece.start_s + onset

    def _backchannels(self, turn: _Piece, next_start_s: float) -> list[_Piece]:
        listener = USER if turn.speaker == AGENT else AGENT
        out = []
        for pause in turn.pauses_s():
            if self.rng.random() >= self.cfg.backchannel_prob:
                continue
            bc = self._backchannel(listener, turn.start_s + pause + self.rng.uniform(0.0, 0.25))
            if bc.start_s + bc.duration_s < next_start_s - 0.1:
                out.append(bc)
        return out

    def build(self, duration_s: float) -> Conversation:
        cfg, rng = self.cfg, self.rng
        pieces: list[_Piece] = []
        t = rng.uniform(0.3, 1.0)
        speaker = AGENT if rng.random() < 0.5 else USER
        while t < duration_s:
            turn = self._turn(speaker, t)
            barge = self._interrupt(turn)
            if barge is not None:
                next_start = barge
            else:
                gap = float(np.clip(rng.normal(cfg.turn_gap_mean_s, cfg.turn_gap_std_s), *cfg.turn_gap_range_s))
                next_start = max(turn.start_s + turn.duration_s + gap, turn.start_s + 0.5)
            pieces += [turn, *self._backchannels(turn, next_start)]
            t, speaker = next_start, USER if speaker == AGENT else AGENT
        return self._mix(pieces, duration_s)

    def _mix(self, pieces: list[_Piece], duration_s: float) -> Conversation:
        sr = self.cfg.audio_sample_rate_hz
        n = int(round(duration_s * sr))
        channels = {AGENT: np.zeros(n, np.float32), USER: np.zeros(n, np.float32)}
        words, turns = [], []
        for p in sorted(pieces, key=lambda p: p.start_s):
            first = int(round(p.start_s * sr))
            if first >= n:
                continue
            seg = p.pcm[: n - first]
            channels[p.speaker][first : first + len(seg)] += seg
            dt = first / sr
            placed = [w for w in _shift(p.words, dt) if w.start_s < duration_s - 0.05]
            placed = [
                SpokenWord(
                    w.word, w.speaker, w.start_s, min(w.end_s, duration_s), min(w.peak_s, duration_s), w.stressed
                )
                for w in placed
            ]
            if not placed:
                continue
            words += placed
            spans = tuple((a + dt, min(b + dt, duration_s)) for a, b in p.sentence_spans_s if a + dt < duration_s)
            turns.append(Turn(p.speaker, placed[0].start_s, placed[-1].end_s, p.kind, p.interrupted, spans))
        for pcm in channels.values():
            np.clip(pcm, -1.0, 1.0, out=pcm)
        words.sort(key=lambda w: (w.start_s, w.speaker))
        turns.sort(key=lambda t: (t.start_s, t.speaker))
        return Conversation(duration_s, sr, channels, tuple(words), tuple(turns))


def build_conversation(cfg: SynthConfig, rng: np.random.Generator, duration_s: float) -> Conversation:
    return ConversationBuilder(cfg, rng).build(duration_s)


def activity_frames(words: tuple[SpokenWord, ...], n_frames: int, fps: float, bridge_s: float = 0.3) -> np.ndarray:
    """(n_frames,) uint8 voice activity: frames inside a word, with gaps shorter than ``bridge_s`` filled."""
    active = np.zeros(n_frames, np.uint8)
    spans: list[list[float]] = []
    for w in sorted(words, key=lambda w: w.start_s):
        if spans and w.start_s - spans[-1][1] < bridge_s:
            spans[-1][1] = max(spans[-1][1], w.end_s)
        else:
            spans.append([w.start_s, w.end_s])
    centres = (np.arange(n_frames) + 0.5) / fps
    for a, b in spans:
        active[(centres >= a) & (centres < b)] = 1
    return active
