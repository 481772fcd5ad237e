"""Options of the synthetic dyadic conversation generator (YAML: ecas/configs/data/synthetic.yaml)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ecas.core.body import COLLARS, NECK_HEAD, SPINE, WRISTS
from ecas.core.config import ConfigError, build_dataclass, load_yaml
from ecas.core.timing import MOTION_FPS

GESTURE_FAMILIES = ("beat", "presentation", "deictic", "size", "adaptor")
# The joints whose micro-motion the agent adds at run time (gesture.layers.micro_motion) rather than through its
# codecs: the spine, neck, collars, head and wrists. The data's ``gesture_poses`` leave it out; the codecs and the
# LM learn those.
LAYERED_MICRO_JOINTS = tuple(sorted(SPINE + NECK_HEAD + COLLARS + WRISTS))  # (3, 6, 9, 12, 13, 14, 15, 20, 21)


@dataclass(frozen=True)
class SynthConfig:
    """Who speaks, how turns are timed, and how lively the agent moves."""

    audio_sample_rate_hz: int = 16_000
    motion_fps: int = MOTION_FPS
    agent_voices: tuple[str, ...] = ("en-us", "en-us+m3", "en-us+klatt2", "en-gb-x-rp")
    user_voices: tuple[str, ...] = ("en-us+f3", "en-gb-x-rp+f2", "en-us+f4", "en-029+f1")
    rate_wpm: tuple[int, int] = (150, 190)  # drawn per speaker and session
    pitch: tuple[int, int] = (35, 65)
    sentences_per_turn: tuple[int, int] = (1, 3)
    sentence_pause_s: tuple[float, float] = (0.15, 0.6)
    turn_gap_mean_s: float = 0.3  # gaps between turns ~ N(mean, std) clipped; negative = overlap
    turn_gap_std_s: float = 0.35
    turn_gap_range_s: tuple[float, float] = (-0.4, 1.4)
    backchannel_prob: float = 0.4  # per pause of the partner's turn
    interruption_prob: float = 0.15  # per agent turn: the user barges in and the agent stops mid-word
    reaction_s: tuple[float, float] = (0.2, 0.5)  # user onset -> agent stops
    gesture_prob: float = 0.85  # per agent sentence
    family_weights: tuple[float, ...] = (0.4, 0.2, 0.12, 0.16, 0.12)  # in GESTURE_FAMILIES order
    amplitude: tuple[float, float] = (0.7, 1.6)  # per gesture, relative
    test_fraction: float = 0.1  # the last sessions go to the test split
    speaker_name: str = "synth"  # take ids are <speaker_number>_<speaker_name>_0_<k>_<k>
    speaker_number: int = 31

    def __post_init__(self) -> None:
        if self.audio_sample_rate_hz <= 0:
            raise ConfigError(f"synthetic.audio_sample_rate_hz: must be > 0, got {self.audio_sample_rate_hz}")
        if self.motion_fps <= 0:
            raise ConfigError(f"synthetic.motion_fps: must be > 0, got {self.motion_fps}")
        for name in ("agent_voices", "user_voices"):
            if not getattr(self, name):
                raise ConfigError(f"synthetic.{name}: needs at least one espeak-ng voice")
        for name in (
            "rate_wpm",
            "pitch",
            "sentences_per_turn",
            "sentence_pause_s",
            "turn_gap_range_s",
            "reaction_s",
            "amplitude",
        ):
            low, high = getattr(self, name)
            if low > high or low < 0 and name != "turn_gap_range_s":
                raise ConfigError(f"synthetic.{name}: expected 0 <= low <= high, got {getattr(self, name)}")
        if self.sentences_per_turn[0] < 1:
            raise ConfigError(f"synthetic.sentences_per_turn: must start at >= 1, got {self.sentences_per_turn}")
        for name in ("backchannel_prob", "interruption_prob", "gesture_prob", "test_fraction"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"synthetic.{name}: must be in [0, 1], got {getattr(self, name)}")
        if (
            len(self.family_weights) != len(GESTURE_FAMILIES)
            or min(self.family_weights) < 0
            or sum(self.family_weights) <= 0
        ):
            raise ConfigError(
                f"synthetic.family_weights: need {len(GESTURE_FAMILIES)} non-negative weights "
                f"({', '.join(GESTURE_FAMILIES)}), got {self.family_weights}"
            )
        if "_" in self.speaker_name or not self.speaker_name:
            raise ConfigError(f"synthetic.speaker_name: must be non-empty without '_', got {self.speaker_name!r}")


def build_synth_config(mapping: Mapping[str, Any] | None) -> SynthConfig:
    return build_dataclass(SynthConfig, mapping, "synthetic")


def load_synth_config(path: str | Path) -> SynthConfig:
    """Read a YAML file whose top level (or `synthetic:` section) holds SynthConfig options."""
    tree = load_yaml(Path(path))
    return build_synth_config(tree.get("synthetic", tree))
