"""The public engine: the agent's voice in, the avatar's motion out, 80 ms at a time.

    from ecas import Engine, Word

    engine = Engine.from_config()                    # the agent's defaults, runtime layers and checkpoints
    for chunk in chunks:                             # any size; mono float32 or int16; 24 kHz or sample_rate_hz=
        for step in engine.feed(chunk, words=words_of(chunk)):
            show(step.poses, step.trans, step.expressions)   # two frames at 25 fps
    engine.flush()                                   # the last partial step, completed with silence
    engine.close()

Each step runs what the agent runs: the local dialogue backend's conditioner, then the gesture stage's generator.
- The agent's audio becomes the speech tokenizer's 8 codes (`dialogue.speech_tokenizer.StreamingSpeechEncoder`,
  the codes the local and playback backends send to the gesture stage).
- Words with times become one text token per step, placed as the dialogue's speaker places them (`WordTrack`).
- The generator of `gesture.build.build_generator` turns (text token, codes, the step's audio) into 20 gesture
  tokens, decodes two frames and runs the runtime layers.
Audio at another rate is resampled causally to 24 kHz (`dialogue.resample.StreamResampler`), so the chunk sizes
never change the result. A session fed by a stage with a conditioner of its own (Moshi, the dialogue stage) calls
`step_conditioned` with that stage's text token and codes instead. The user's audio is checked and accepted, but
the LM is conditioned on the agent's speech only (text and audio tokens, as MIBURI's), so it does not move the avatar.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from dialogue.backend import condition_spec
from dialogue.config import DialogueConfig
from dialogue.resample import StreamResampler
from dialogue.speech_tokenizer import DEFAULT_CHECKPOINT, SpeechTokenizer, StreamingSpeechEncoder
from dialogue.text_vocab import LOCAL_SPEC, word_token
from ecas.core.config import apply_override, build_dataclass, load_yaml, parse_override
from ecas.core.paths import DEFAULT_CONFIG, PACKAGE_DIR
from ecas.core.spec import ConditionSpec
from ecas.core.timing import FRAMES_PER_STEP, SAMPLE_RATE_HZ, STEP_S, STEP_SAMPLES
from gesture.build import build_generator
from gesture.config import GestureConfig, IdleGateConfig
from gesture.generator import GestureGenerator

MAX_PENDING_WORDS = 1024  # words given ahead of their audio wait in a buffer of this size
INT16_FULL_SCALE = 32768.0


@dataclass(frozen=True)
class Word:
    """A word the agent says, on the engine's agent-audio clock (seconds since the first sample fed)."""

    text: str
    start_s: float
    end_s: float


@dataclass(frozen=True, eq=False)
class MotionStep:
    """One 80 ms step: two frames at 25 fps. The arrays are read-only."""

    step: int  # index since reset
    t_audio_s: float  # the step's start on the agent-audio clock
    poses: np.ndarray  # (2, 55, 3) float32 axis-angle, SMPL-X joint order
    trans: np.ndarray  # (2, 3) float32, metres
    expressions: np.ndarray  # (2, 100) float32 expression coefficients
    speaking: bool  # the agent's voice is active in this step
    text_token: int = field(default=-1, kw_only=True)  # the step's text token (-1: none)
    tokens: np.ndarray | None = field(default=None, kw_only=True)  # (20,) int32 gesture tokens (LM level order)
    va_prob: float = field(default=math.nan, kw_only=True)  # the LM's voice-activity head (NaN without one)


@dataclass
class EngineState:
    """What the engine carries from call to call; its buffers are allocated once."""

    agent: np.ndarray = field(default_factory=lambda: np.zeros(STEP_SAMPLES, np.float32))  # the partial step
    filled: int = 0  # samples of `agent` filled so far
    step: int = 0  # steps completed since reset
    rate_hz: int | None = None  # the input sample rate of this session, fixed by its first feed
    source: str | None = None  # "audio" (feed, step) or "codes" (step_conditioned): one per session

    def reset(self) -> None:
        self.agent[:] = 0.0
        self.filled = self.step = 0
        self.rate_hz = self.source = None


class WordTrack:
    """Words with times -> one text token per step, placed as `dialogue.speaker.Speaker` places them: a word's token
    goes to the step that holds its first sample (round(start_s * 24 kHz) // 1920) or, when an earlier word took that
    step, to the next free one. Pending words sit in preallocated arrays, sorted by their first sample."""

    def __init__(self, capacity: int = MAX_PENDING_WORDS) -> None:
        self.starts = np.zeros(capacity, np.int64)  # first sample of each pending word, ascending
        self.tokens = np.zeros(capacity, np.int64)
        self.count = 0

    def reset(self) -> None:
        self.count = 0

    def add(self, words: Sequence[Word]) -> None:
        """Keep `words` until their step; all are checked (and room made sure of) before any is kept."""
        checked = check_words(words)
        if self.count + len(checked) > len(self.starts):
            raise ValueError(
                f"words: more than {len(self.starts)} words wait for their audio; feed the audio they belong to"
            )
        for start, token in checked:
            at = int(np.searchsorted(self.starts[: self.count], start, side="right"))  # after equal starts: in order
            self.starts[at + 1 : self.count + 1] = self.starts[at : self.count]
            self.tokens[at + 1 : self.count + 1] = self.tokens[at : self.count]
            self.starts[at], self.tokens[at] = start, token
            self.count += 1

    def take(self, step: int) -> int:
        """The token of `step`: the earliest pending word that started before the step's end, else -1."""
        if self.count == 0 or self.starts[0] >= (step + 1) * STEP_SAMPLES:
            return -1
        token = int(self.tokens[0])
        self.starts[: self.count - 1] = self.starts[1 : self.count]
        self.tokens[: self.count - 1] = self.tokens[1 : self.count]
        self.count -= 1
        return token


class Engine:
    """See the module docstring. Build one with `from_config` (a YAML config) or `from_sections` (config sections);
    the constructor takes a built generator and, for `feed`/`step`, the speech tokenizer."""

    def __init__(
        self,
        generator: GestureGenerator,
        *,
        tokenizer: SpeechTokenizer | None = None,
        silence_rms: float | None = None,
    ) -> None:
        self.generator = generator
        self.encoder = StreamingSpeechEncoder(tokenizer) if tokenizer is not None else None
        # a step is `speaking` when a frame of its agent audio is louder than this (default: the idle gate's silence)
        self.silence_rms = _silence_rms(IdleGateConfig()) if silence_rms is None else silence_rms
        self.words = WordTrack()
        self.state = EngineState()
        self._resampler: StreamResampler | None = None
        self._closed = False

    @classmethod
    def from_config(cls, config: str | Path | None = None, overrides: Sequence[str] = (), seed: int = 0) -> Engine:
        """The engine of a YAML config (None: the packaged default), with `section.key=value` overrides as `--set`
        gives them: its `gesture:` section and its `dialogue:` section's speech tokenizer, as the agent runs them."""
        tree = load_yaml(Path(config) if config is not None else DEFAULT_CONFIG)
        for text in overrides:
            apply_override(tree, *parse_override(text))
        gesture = build_dataclass(GestureConfig, tree.get("gesture"), "gesture")
        dialogue = build_dataclass(DialogueConfig, tree.get("dialogue"), "dialogue")
        return cls.from_sections(gesture, dialogue, seed=seed)

    @classmethod
    def from_sections(
        cls,
        gesture: GestureConfig,
        dialogue: DialogueConfig | None = None,
        *,
        seed: int = 0,
        conditioner: bool = True,
    ) -> Engine:
        """The engine of a `gesture:` section, warmed up. With `conditioner` (and a dialogue backend whose codes are
        the local speech tokenizer's), it loads the `dialogue:` section's speech tokenizer for `feed`/`step`;
        without, it only runs `step_conditioned` (the gesture stage, whose dialogue stage computes the codes)."""
        torch.set_num_threads(1)
        dialogue = dialogue if dialogue is not None else DialogueConfig()
        spec = condition_spec(dialogue)
        conditioner = conditioner and spec == LOCAL_SPEC
        if gesture.dialogue_spec is None and conditioner:
            gesture = dataclasses.replace(gesture, dialogue_spec=spec)
        gesture = _packaged_paths(gesture)
        tokenizer = None
        if conditioner:
            path = dialogue.speech_tokenizer
            tokenizer = SpeechTokenizer.load(_packaged(Path(path)) if path else DEFAULT_CHECKPOINT)
        engine = cls(build_generator(gesture, seed), tokenizer=tokenizer, silence_rms=_silence_rms(gesture.idle))
        engine.warm_up(gesture.warmup_steps)
        return engine

    @property
    def spec(self) -> ConditionSpec:
        """What the LM is conditioned on (the dialogue backend's text and audio vocabulary)."""
        return self.generator.spec

    def warm_up(self, steps: int) -> None:
        """Run `steps` silent steps, then reset: first-call allocations happen before the stream."""
        silence = np.zeros(STEP_SAMPLES, np.float32)
        no_codes = np.full(self.spec.n_audio_codebooks, -1)
        for _ in range(steps):
            if self.encoder is not None:
                self.encoder.step(silence)
            self.generator.step(-1, no_codes, silence)
        self.reset()

    def reset(self) -> None:
        """Start a new session: the step count, the audio clock, pending words and every model's state."""
        self._check_open()
        self.state.reset()
        self.words.reset()
        if self._resampler is not None:
            self._resampler.reset()
        if self.encoder is not None:
            self.encoder.reset()
        self.generator.reset()

    def feed(
        self,
        agent_pcm: np.ndarray,
        *,
        user_pcm: np.ndarray | None = None,
        words: Sequence[Word] = (),
        sample_rate_hz: int = SAMPLE_RATE_HZ,
    ) -> list[MotionStep]:
        """Audio as it arrives, any chunk size: returns the steps it completed (none until 1920 samples at 24 kHz
        are in). `words` are the agent's words with their times, given with or ahead of their audio. `user_pcm` (at
        `sample_rate_hz` too, any length, also alone with an empty `agent_pcm`) is checked; the LM does not use it."""
        pcm = as_mono_float32(agent_pcm, "agent_pcm")
        rate = _check_rate(sample_rate_hz, self.state.rate_hz if len(pcm) else None)  # user audio alone: any rate
        if user_pcm is not None:
            as_mono_float32(user_pcm, "user_pcm")
        check_words(words)
        self._check_source("audio", "feed")
        self.words.add(words)
        self.state.source = "audio"
        if not len(pcm):
            return []
        self.state.rate_hz = rate
        pcm = self._to_24k(pcm, rate)
        out = []
        used = 0
        while used < len(pcm):
            take = min(STEP_SAMPLES - self.state.filled, len(pcm) - used)
            self.state.agent[self.state.filled : self.state.filled + take] = pcm[used : used + take]
            self.state.filled += take
            used += take
            if self.state.filled == STEP_SAMPLES:
                out.append(self._audio_step())
        return out

    def step(
        self, agent_pcm: np.ndarray, *, user_pcm: np.ndarray | None = None, words: Sequence[Word] = ()
    ) -> MotionStep:
        """Exactly one step: STEP_SAMPLES (1920) samples at 24 kHz."""
        pcm = as_mono_float32(agent_pcm, "agent_pcm")
        if pcm.shape != (STEP_SAMPLES,):
            raise ValueError(f"agent_pcm: step takes exactly {STEP_SAMPLES} samples at 24 kHz, got {len(pcm)}")
        self._check_source("audio", "step")
        if self.state.filled:
            raise ValueError(f"step: {self.state.filled} samples of a partial step from feed() wait; use feed()")
        if self.state.rate_hz not in (None, SAMPLE_RATE_HZ):
            raise ValueError(f"step: this session is fed at {self.state.rate_hz} Hz; step takes 24 kHz; use feed()")
        (motion,) = self.feed(pcm, user_pcm=user_pcm, words=words)
        return motion

    def step_conditioned(
        self, text_token: int, agent_codes, agent_pcm: np.ndarray | None = None, *, speaking: bool | None = None
    ) -> MotionStep:
        """One step from a conditioner of the caller's own: the step's text token (-1: none), its `spec`'s 8 audio
        codes (-1: none) and the step's agent audio (24 kHz, for the layers that follow the voice). `speaking`
        defaults to the audio's loudness."""
        pcm = None
        if agent_pcm is not None:
            pcm = as_mono_float32(agent_pcm, "agent_pcm")
            if pcm.shape != (STEP_SAMPLES,):
                raise ValueError(f"agent_pcm: a step is {STEP_SAMPLES} samples at 24 kHz, got {len(pcm)}")
        self._check_source("codes", "step_conditioned")
        if speaking is None:
            speaking = pcm is not None and self._loud(pcm)
        motion = self._generate(int(text_token), agent_codes, pcm, bool(speaking))  # the generator checks the codes
        self.state.source = "codes"
        return motion

    def flush(self) -> list[MotionStep]:
        """Complete a partial step with silence; returns it (or nothing when no partial step waits)."""
        self._check_open()
        if not self.state.filled:
            return []
        self.state.agent[self.state.filled :] = 0.0
        return [self._audio_step()]

    def close(self) -> None:
        if not self._closed:
            self.generator.close()
            self._closed = True

    def __enter__(self) -> Engine:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ inside

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("engine: closed; build a new one")

    def _check_source(self, source: str, call: str) -> None:
        """A session is conditioned by the engine (feed, step) or by the caller (step_conditioned), not both."""
        self._check_open()
        if source == "audio" and self.encoder is None:
            raise RuntimeError(
                f"{call}: this engine has no conditioner (LM spec {self.spec.name!r}, or built with "
                f"conditioner=False); give the codes with step_conditioned"
            )
        if self.state.source not in (None, source):
            raise RuntimeError(f"{call}: this session is driven by {self.state.source}; call reset() first")

    def _to_24k(self, pcm: np.ndarray, rate: int) -> np.ndarray:
        if rate == SAMPLE_RATE_HZ:
            return pcm
        if self._resampler is None or (self._resampler.up, self._resampler.down) != _ratio(rate):
            self._resampler = StreamResampler(rate, SAMPLE_RATE_HZ)
        return self._resampler.process(pcm)

    def _loud(self, pcm: np.ndarray) -> bool:
        frames = pcm.reshape(FRAMES_PER_STEP, -1)  # (2, 960): the step's two motion frames
        return bool(np.sqrt(np.mean(np.square(frames, dtype=np.float64), axis=1)).max() > self.silence_rms)

    def _audio_step(self) -> MotionStep:
        pcm = self.state.agent
        self.state.filled = 0
        codes = self.encoder.step(pcm)
        return self._generate(self.words.take(self.state.step), codes, pcm, self._loud(pcm))

    def _generate(self, text_token: int, codes, pcm: np.ndarray | None, speaking: bool) -> MotionStep:
        out = self.generator.step(text_token, codes, pcm)
        step = self.state.step
        self.state.step += 1
        return MotionStep(
            step,
            step * STEP_S,
            _frozen(out.poses, np.float32),
            _frozen(out.trans, np.float32),
            _frozen(out.expressions, np.float32),
            speaking,
            text_token=text_token,
            tokens=_frozen(out.tokens, np.int32),
            va_prob=float(out.va_prob),
        )


# ---------------------------------------------------------------------- checks


def as_mono_float32(pcm, name: str) -> np.ndarray:
    """Mono audio (N,) or (N, 1), float (in [-1, 1]) or int16 -> finite float32 (N,); errors name the argument."""
    a = np.asarray(pcm)
    if a.ndim == 2 and a.shape[1] == 1:
        a = a[:, 0]
    if a.ndim != 1:
        raise ValueError(f"{name}: expected mono audio of shape (N,) or (N, 1), got shape {a.shape} (mix down first)")
    if a.dtype == np.int16:
        return a.astype(np.float32) / INT16_FULL_SCALE
    if a.dtype.kind != "f":
        raise ValueError(f"{name}: expected float32 (or float64) in [-1, 1] or int16 samples, got dtype {a.dtype}")
    a = a.astype(np.float32, copy=False)
    if not np.isfinite(a).all():
        raise ValueError(f"{name}: contains NaN or infinite samples")
    return a


def _check_rate(rate, session_rate: int | None) -> int:
    if isinstance(rate, bool) or not isinstance(rate, (int, np.integer)) or rate <= 0:
        raise ValueError(f"sample_rate_hz: must be a positive integer, got {rate!r}")
    if session_rate is not None and rate != session_rate:
        raise ValueError(f"sample_rate_hz: this session is fed at {session_rate} Hz, got {rate}; reset() to change")
    return int(rate)


def check_words(words: Sequence[Word]) -> list[tuple[int, int]]:
    """(first sample at 24 kHz, text token) of each word; errors name the word and its field."""
    out = []
    for i, word in enumerate(words):
        if not all(hasattr(word, a) for a in ("text", "start_s", "end_s")):
            raise ValueError(f"words[{i}]: expected a Word(text, start_s, end_s), got {word!r}")
        start, end = float(word.start_s), float(word.end_s)
        if not (math.isfinite(start) and start >= 0):
            raise ValueError(f"words[{i}].start_s: must be finite and >= 0, got {word.start_s}")
        if not (math.isfinite(end) and end >= start):
            raise ValueError(f"words[{i}].end_s: must be finite and >= start_s ({start}), got {word.end_s}")
        out.append((int(round(start * SAMPLE_RATE_HZ)), word_token(word.text)))
    return out


def _silence_rms(idle: IdleGateConfig) -> float:
    """The idle gate's silence (an L2 norm over its window) as the RMS of a sample."""
    return idle.l2_threshold / math.sqrt(idle.window_samples)


def _ratio(rate: int) -> tuple[int, int]:
    g = math.gcd(rate, SAMPLE_RATE_HZ)
    return SAMPLE_RATE_HZ // g, rate // g


def _frozen(array, dtype) -> np.ndarray:
    out = np.array(array, dtype)  # a copy: later steps never touch it
    out.flags.writeable = False
    return out


def _packaged(path: Path) -> Path:
    """A relative path that is not found from the working directory is taken from beside the installed package."""
    if path.is_absolute() or path.exists():
        return path
    beside = PACKAGE_DIR.parent / path
    return beside if beside.exists() else path


def _packaged_paths(cfg: GestureConfig) -> GestureConfig:
    paths = {
        key: _packaged(Path(getattr(cfg, key)))
        for key in ("lm_checkpoint", "codec_checkpoints")
        if getattr(cfg, key) is not None
    }
    if cfg.idle.slices_dir is not None:
        paths["idle"] = dataclasses.replace(cfg.idle, slices_dir=_packaged(Path(cfg.idle.slices_dir)))
    return dataclasses.replace(cfg, **paths)


__all__ = ["Engine", "EngineState", "MotionStep", "Word", "WordTrack", "as_mono_float32"]
