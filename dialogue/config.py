"""Options of the `dialogue:` section of the YAML config."""

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ecas.core.config import ConfigError


def _require(cond: bool, key: str, message: str) -> None:
    if not cond:
        raise ConfigError(f"dialogue.{key}: {message}")


@dataclass(frozen=True)
class VadConfig:
    """Silero VAD probabilities drive QUIET -> STARTING -> SPEAKING -> STOPPING -> QUIET."""

    start_threshold: float = 0.5  # probability that counts as speech
    stop_threshold: float = 0.35  # probability below which it counts as silence (hysteresis)
    start_s: float = 0.15  # speech needed in STARTING before SPEAKING
    stop_s: float = 0.6  # silence needed in STOPPING before QUIET (end of the user's turn)

    def __post_init__(self):
        _require(
            0 < self.stop_threshold <= self.start_threshold < 1,
            "vad.stop_threshold",
            f"need 0 < stop_threshold <= start_threshold < 1, got {self.stop_threshold}, {self.start_threshold}",
        )
        _require(self.start_s >= 0, "vad.start_s", f"must be >= 0, got {self.start_s}")
        _require(self.stop_s > 0, "vad.stop_s", f"must be > 0, got {self.stop_s}")


@dataclass(frozen=True)
class TurnConfig:
    """When the user's turn ends (dialogue/end_of_turn.py).

    detector "silence": after `vad.stop_s` of silence. "smart_turn": after `min_wait_s` of silence the smart-turn
    model judges the user's recent audio; a probability >= `threshold` ends the turn there, otherwise the agent
    keeps listening until the user speaks again or `max_wait_s` of silence have passed.
    """

    detector: Literal["silence", "smart_turn"] = "smart_turn"
    threshold: float = 0.5  # probability of a complete turn that ends it
    min_wait_s: float = 0.2  # silence before the model is asked
    max_wait_s: float = 2.0  # silence after which the turn ends anyway
    model: str | None = None  # an ONNX file; None: ecas/checkpoints/smart_turn/smart-turn-v3.2-cpu.onnx

    def __post_init__(self):
        _require(0 < self.threshold < 1, "turn.threshold", f"must be in (0, 1), got {self.threshold}")
        _require(0 < self.min_wait_s <= 2.0, "turn.min_wait_s", f"must be in (0, 2], got {self.min_wait_s}")
        _require(
            self.min_wait_s <= self.max_wait_s <= 10.0,
            "turn.max_wait_s",
            f"must be in [min_wait_s, 10] = [{self.min_wait_s}, 10], got {self.max_wait_s}",
        )


@dataclass(frozen=True)
class EchoConfig:
    """Echo suppression for loudspeakers: the agent's own played voice must not trigger barge-in.

    mode "gate": the mic is compared with the agent's known playback signal (dialogue/echo.py): the echo's
    level relative to the playback is learned from blocks where the mic clearly is the playback, and the VAD
    only counts speech `margin_db` louder than the loudest echo the playback could cause. Harmless without
    echo (headphones, replayed input), where it never engages. "off": no gating.
    """

    mode: Literal["off", "gate"] = "gate"
    max_delay_s: float = 0.8  # the longest playback -> microphone delay (speaker and mic buffers, bus)
    margin_db: float = 6.0  # how much louder than the loudest possible echo the user must be

    def __post_init__(self):
        _require(0 < self.max_delay_s <= 2.0, "echo.max_delay_s", f"must be in (0, 2], got {self.max_delay_s}")


@dataclass(frozen=True)
class AsrConfig:
    """pocketsphinx; None uses the en-us model inside the wheel."""

    hmm: str | None = None
    lm: str | None = None
    dict: str | None = None
    # Search limits: with these, a step's decoding stays under ~30 ms CPU (p99) at the same accuracy on
    # librivox_0870 as the defaults (whose p99 is ~140 ms).
    max_hmm_per_frame: int = 2000
    max_words_per_frame: int = 8
    phone_lookahead_frames: int = 5
    budget_steps: float = 1.5  # audio decoded per step, in steps: a backlog (pre-roll) is caught up gradually

    def __post_init__(self):
        _require(self.budget_steps > 1.0, "asr.budget_steps", f"must be > 1 to catch up, got {self.budget_steps}")
        _require(
            self.max_hmm_per_frame >= 100, "asr.max_hmm_per_frame", f"must be >= 100, got {self.max_hmm_per_frame}"
        )


@dataclass(frozen=True)
class TtsConfig:
    voice: str = "en-us+f3"
    rate_wpm: int = 165
    pitch: int = 55

    def __post_init__(self):
        _require(80 <= self.rate_wpm <= 450, "tts.rate_wpm", f"must be in [80, 450], got {self.rate_wpm}")
        _require(0 <= self.pitch <= 100, "tts.pitch", f"must be in [0, 100], got {self.pitch}")


@dataclass(frozen=True)
class ResponderConfig:
    """`rules`: built-in small talk. `openai`: any OpenAI-compatible /v1/chat/completions endpoint, streamed."""

    kind: Literal["rules", "openai"] = "rules"
    url: str = "http://127.0.0.1:8080/v1/chat/completions"
    model: str = "default"
    api_key_env: str = "OPENAI_API_KEY"  # name of the environment variable holding the key, if any
    timeout_s: float = 4.0
    max_tokens: int = 80
    system_prompt: str = (
        "You are a friendly embodied agent having a spoken conversation. "
        "Answer in one to three short sentences of plain spoken English."
    )
    fallback_text: str = "Sorry, I can't reach my language model right now. Could you say that again in a moment?"

    def __post_init__(self):
        _require(self.timeout_s > 0, "responder.timeout_s", f"must be > 0, got {self.timeout_s}")
        _require(
            self.url.startswith(("http://", "https://")), "responder.url", f"must be an http(s) URL, got {self.url!r}"
        )


@dataclass(frozen=True)
class PlaybackConfig:
    """The agent speaks a recording; text tokens from `transcript` (whisper json, TextGrid or plain text)."""

    speak: Path | None = None
    transcript: Path | None = None
    start_s: float = 0.0  # when the agent starts speaking, from the first step


@dataclass(frozen=True)
class MoshiConfig:
    """Local files only: the LM weights, Mimi weights and the sentencepiece text tokenizer."""

    lm_weights: Path | None = None  # e.g. model.safetensors
    mimi_weights: Path | None = None  # e.g. tokenizer-e351c8d8-checkpoint125.safetensors
    tokenizer: Path | None = None  # e.g. tokenizer_spm_32k_3.model
    lm_config: Path | None = None  # a json of LM kwargs for non-default model sizes (None: Moshi 7B)
    mimi_config: Path | None = None  # a json of Mimi kwargs (None: the released Mimi)
    device: str = "cpu"
    temp: float = 0.8
    temp_text: float = 0.7
    top_k: int = 250
    top_k_text: int = 25
    cfg_coef: float = 1.0

    def __post_init__(self):
        _require(self.temp >= 0 and self.temp_text >= 0, "moshi.temp", "temperatures must be >= 0")
        _require(self.cfg_coef >= 0, "moshi.cfg_coef", f"must be >= 0, got {self.cfg_coef}")


@dataclass(frozen=True)
class DialogueConfig:
    backend: Literal["local", "moshi", "playback"] = "local"
    barge_in_s: float = 0.3  # user speech over the agent longer than this stops the agent
    speech_tokenizer: Path | None = None  # None: ecas/checkpoints/speech_tokenizer/speech_tokenizer.safetensors
    transcript_name: str = "transcript.json"
    vad: VadConfig = field(default_factory=VadConfig)
    turn: TurnConfig = field(default_factory=TurnConfig)
    echo: EchoConfig = field(default_factory=EchoConfig)
    asr: AsrConfig = field(default_factory=AsrConfig)
    tts: TtsConfig = field(default_factory=TtsConfig)
    responder: ResponderConfig = field(default_factory=ResponderConfig)
    playback: PlaybackConfig = field(default_factory=PlaybackConfig)
    moshi: MoshiConfig = field(default_factory=MoshiConfig)

    def __post_init__(self):
        _require(0 < self.barge_in_s <= 5.0, "barge_in_s", f"must be in (0, 5], got {self.barge_in_s}")
        _require(
            self.backend != "playback" or self.playback.speak is not None,
            "playback.speak",
            "the playback backend needs a recording to speak (--speak FILE)",
        )
