"""The synthetic agent driven by a real recording: its motion for a monologue of given speech.

A recording (e.g. the BEAT2 clip's speech) becomes a one-speaker ``Conversation``: the agent's channel is the
recording, the user's is silent, the words and their timings come from the local recogniser (pocketsphinx, as
in the ``playback`` backend), each word's energy peak is found as in a synthesised sentence, and the words are
grouped into sentences (pauses >= ``SENTENCE_PAUSE_S``) and turns (pauses >= ``TURN_PAUSE_S``). The agent's
motion for it is the synthetic ground truth of that speech (the realism report's reference, gesture.eval.realism).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gesture.data.audio import load_audio
from gesture.synth.agent import AgentMotion, synthesize_agent_motion
from gesture.synth.calibration import MicroNoise
from gesture.synth.config import SynthConfig
from gesture.synth.conversation import (
    AGENT,
    ENVELOPE_HOP_S,
    STROKE_SEARCH_S,
    USER,
    Conversation,
    SpokenWord,
    Turn,
    envelope,
    is_stressed,
)

RECOGNISER_RATE_HZ = 24_000  # the rate the playback backend recognises at
SENTENCE_PAUSE_S = 0.5
TURN_PAUSE_S = 1.5


@dataclass(frozen=True)
class TimedWord:
    word: str
    start_s: float
    end_s: float


def recognised_words(path: Path | str) -> list[TimedWord]:
    """The recording's words with their timings, by the local recogniser (as the playback backend hears it)."""
    from dialogue.alignment import recognize

    pcm = load_audio(path, RECOGNISER_RATE_HZ)
    return [TimedWord(w.word, w.start_s, w.end_s) for w in recognize(pcm, RECOGNISER_RATE_HZ)]


def _spoken(words: list[TimedWord], pcm: np.ndarray, sample_rate_hz: int) -> list[SpokenWord]:
    env = envelope(pcm, sample_rate_hz)  # (hops,)
    out = []
    for w in words:
        a = int(w.start_s / ENVELOPE_HOP_S)
        search = env[a : a + int(STROKE_SEARCH_S / ENVELOPE_HOP_S)]
        peak_s = (a + int(np.argmax(search))) * ENVELOPE_HOP_S if len(search) else w.start_s
        out.append(
            SpokenWord(
                w.word, AGENT, w.start_s, max(w.end_s, w.start_s + 0.03), min(peak_s, w.end_s), is_stressed(w.word)
            )
        )
    return out


def _split(words: list[SpokenWord], pause_s: float) -> list[list[SpokenWord]]:
    groups: list[list[SpokenWord]] = []
    for w in words:
        if groups and w.start_s - groups[-1][-1].end_s < pause_s:
            groups[-1].append(w)
        else:
            groups.append([w])
    return groups


def monologue(pcm: np.ndarray, sample_rate_hz: int, words: list[TimedWord]) -> Conversation:
    """A conversation in which the agent says ``pcm`` (with ``words``) and the user stays silent."""
    duration_s = len(pcm) / sample_rate_hz
    spoken = _spoken([w for w in words if w.start_s < duration_s], pcm, sample_rate_hz)
    turns = []
    for turn_words in _split(spoken, TURN_PAUSE_S):
        spans = tuple((s[0].start_s, s[-1].end_s) for s in _split(turn_words, SENTENCE_PAUSE_S))
        turns.append(Turn(AGENT, turn_words[0].start_s, turn_words[-1].end_s, "turn", False, spans))
    channels = {AGENT: pcm.astype(np.float32), USER: np.zeros(len(pcm), np.float32)}
    return Conversation(duration_s, sample_rate_hz, channels, tuple(spoken), tuple(turns))


def motion_for_recording(
    path: Path | str,
    seed: int = 0,
    cfg: SynthConfig | None = None,
    words: list[TimedWord] | None = None,
    micro: dict[int, MicroNoise] | None = None,
) -> tuple[Conversation, AgentMotion]:
    """The synthetic agent's motion (25 fps) while it says the recording at ``path`` (``words``: its timed words,
    recognised when not given; ``micro``: see ``synthesize_agent_motion``)."""
    cfg = cfg or SynthConfig()
    pcm = load_audio(path, cfg.audio_sample_rate_hz)
    conv = monologue(pcm, cfg.audio_sample_rate_hz, recognised_words(path) if words is None else words)
    return conv, synthesize_agent_motion(cfg, np.random.default_rng([seed, 0]), conv, micro=micro)
