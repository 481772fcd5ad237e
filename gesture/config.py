"""Options of the `gesture:` section of the YAML config: the runtime's checkpoints, sampling, CFG, idle gate and
speaker. The LM's sizes live in `gesture/lm/config.py`, the codecs' in `gesture/codec/config.py`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ecas.core.config import ConfigError
from ecas.core.spec import ConditionSpec
from ecas.core.timing import MOTION_FPS
from gesture.synth.config import LAYERED_MICRO_JOINTS


@dataclass(frozen=True)
class IdleGateConfig:
    """Section 5's idle gate: while the agent is silent, upper and face tokens come from recorded idle slices."""

    enabled: bool = False
    slices_dir: Path | None = None  # holds idle_upper_tokens_slices.npz and idle_face_tokens_slices.npz
    window_samples: int = 5760  # 3 steps of agent audio at 24 kHz
    l2_threshold: float = 0.5
    rewind_below_tokens: int = 12

    def __post_init__(self) -> None:
        if self.enabled and self.slices_dir is None:
            raise ConfigError("gesture.idle.slices_dir: required when gesture.idle.enabled is true")
        if self.window_samples < 1:
            raise ConfigError(f"gesture.idle.window_samples: must be >= 1, got {self.window_samples}")


@dataclass(frozen=True)
class MicroMotionConfig:
    """The micro-motion layer on the decoded pose (gesture.micro_motion; not in the reference, off by default)."""

    enabled: bool = False
    joints: tuple[int, ...] = LAYERED_MICRO_JOINTS  # spine, neck, collars, head, wrists: the training data's layer
    scale: float = 1.0  # times every fitted standard deviation
    # The neck's and head's slow drift (gesture.micro_motion.HeadDrift; 0: none): its std per axis and its cutoff
    head_drift_rad: float = 0.0
    head_drift_hz: float = 0.17
    # The collars' noise cutoff (ecas.core.body.COLLARS; 0: the fitted one, about 3 Hz)
    collar_cutoff_hz: float = 0.0

    def __post_init__(self) -> None:
        if not self.joints:
            raise ConfigError("gesture.micro_motion.joints: must name at least one joint")
        if self.scale < 0:
            raise ConfigError(f"gesture.micro_motion.scale: must be >= 0, got {self.scale}")
        if self.head_drift_rad < 0:
            raise ConfigError(f"gesture.micro_motion.head_drift_rad: must be >= 0, got {self.head_drift_rad}")
        if not 0 < self.head_drift_hz < MOTION_FPS / 2:
            raise ConfigError(
                f"gesture.micro_motion.head_drift_hz: must be in (0, {MOTION_FPS / 2}), got {self.head_drift_hz}"
            )
        if not 0 <= self.collar_cutoff_hz < MOTION_FPS / 2:
            raise ConfigError(
                f"gesture.micro_motion.collar_cutoff_hz: must be 0 (as fitted) or in (0, "
                f"{MOTION_FPS / 2}), got {self.collar_cutoff_hz}"
            )


@dataclass(frozen=True)
class FaceLayerConfig:
    """The face layer on the decoded expressions (gesture.face_layer; not in the reference, off by default)."""

    enabled: bool = False
    # the total rate, the decoded face's own blinks included; the synthetic agent's (gesture.synth.face); 0: none added
    blinks_per_minute: float = 17.0
    brow_cutoff_hz: float = 0.0  # the brow activation's low-pass; 0: as decoded

    def __post_init__(self) -> None:
        if not 0 <= self.blinks_per_minute < 75:
            raise ConfigError(f"gesture.face.blinks_per_minute: must be in [0, 75), got {self.blinks_per_minute}")
        if self.brow_cutoff_hz < 0:
            raise ConfigError(f"gesture.face.brow_cutoff_hz: must be >= 0, got {self.brow_cutoff_hz}")


@dataclass(frozen=True)
class FootLockConfig:
    """Foot locking on the decoded legs (gesture.foot_lock; not in the reference, off by default)."""

    enabled: bool = False
    # A lock lets go when the decoded ankle is this far from where it was planted, while the agent is silent ...
    release_m: float = 0.2
    release_speaking_m: float = 0.18  # ... and while it speaks (gesture.foot_lock)
    blend_s: float = 0.2  # a landing foot's leg turns from decoded to locked over this long
    step_s: float = 0.5  # a released leg turns back to decoded over this long (the step)

    def __post_init__(self) -> None:
        for name in ("release_m", "release_speaking_m", "blend_s", "step_s"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"gesture.foot_lock.{name}: must be > 0, got {getattr(self, name)}")


ARM_JOINTS = (18, 19, 20, 21)  # elbows and wrists
TORSO_AND_LEG_JOINTS = tuple(range(18))  # pelvis, legs, spine, neck, collars, head, shoulders


@dataclass(frozen=True)
class AlternationFilterConfig:
    """The decoded motion's frame-to-frame alternation removed (gesture.alternation_filter; not in the reference,
    off by default)."""

    enabled: bool = False
    joints: tuple[int, ...] = TORSO_AND_LEG_JOINTS  # and the translation; the elbows and wrists: the stabilizer

    def __post_init__(self) -> None:
        if not self.joints:
            raise ConfigError("gesture.alternation_filter.joints: must name at least one joint")


@dataclass(frozen=True)
class StabilizerConfig:
    """Speed-adaptive smoothing of the output arms (gesture.stabilizer; not in the reference, off by default)."""

    enabled: bool = False
    joints: tuple[int, ...] = ARM_JOINTS
    # Per joint of `joints`, the cutoff while it is at rest (elbows, wrists: each group's still fraction matched the
    # ground truth's on validation sessions, synthetic seed 1, sampled without a hold bias) ...
    min_cutoff_hz: tuple[float, ...] = (0.3, 0.3, 2.0, 2.0)
    # ... rising this much per rad/s of its speed: 0.6 since the LM trained on the data whose micro-motion has real
    # motion's spectrum; with 0.3 its elbows on the real clip's speech reached 0.62-0.64 of the speaker's 90th
    # percentile speed (seeds 0 and 3), with 0.6 0.68-0.70 (README, realism section)
    speed_gain_hz: float = 0.6
    speed_cutoff_hz: float = 1.0  # the speed estimate's own smoothing
    # Per joint, how far the input may leave a held output (0: never holds) and the share of it within which a
    # following output settles into a hold. The wrists' 0.08 rad was chosen on validation sessions (synthetic seed 1,
    # while the agent spoke: 1.03 / 0.99 of the ground truth's still share, 0.93 / 0.89 without holds). The elbows'
    # 0.09 centres their still share on the real speaker's on his speech (seeds 0-9: 0.75-1.44, median 0.95; with
    # 0.08, as chosen on validation sessions, 0.63-1.18, median 0.84), at 1.33 / 1.11 of the synthetic ground truth's
    # on validation sessions (README, realism section)
    hold_rad: tuple[float, ...] = (0.09, 0.09, 0.08, 0.08)
    settle_share: float = 0.25

    def __post_init__(self) -> None:
        if not self.joints:
            raise ConfigError("gesture.stabilizer.joints: must name at least one joint")
        if len(self.min_cutoff_hz) != len(self.joints) or min(self.min_cutoff_hz) <= 0:
            raise ConfigError(
                f"gesture.stabilizer.min_cutoff_hz: need one value > 0 per joint of "
                f"gesture.stabilizer.joints ({len(self.joints)}), got {list(self.min_cutoff_hz)}"
            )
        if self.speed_cutoff_hz <= 0:
            raise ConfigError(f"gesture.stabilizer.speed_cutoff_hz: must be > 0, got {self.speed_cutoff_hz}")
        if self.speed_gain_hz < 0:
            raise ConfigError(f"gesture.stabilizer.speed_gain_hz: must be >= 0, got {self.speed_gain_hz}")
        if len(self.hold_rad) != len(self.joints) or min(self.hold_rad) < 0:
            raise ConfigError(
                f"gesture.stabilizer.hold_rad: need one value >= 0 per joint of "
                f"gesture.stabilizer.joints ({len(self.joints)}), got {list(self.hold_rad)}"
            )
        if not 0 < self.settle_share < 1:
            raise ConfigError(f"gesture.stabilizer.settle_share: must be in (0, 1), got {self.settle_share}")


@dataclass(frozen=True)
class GestureConfig:
    """The `gesture:` section: checkpoints, sampling, classifier-free guidance, idle gate, speaker."""

    lm_checkpoint: Path | None = None  # a directory written by `ecas train-lm`
    codec_checkpoints: Path | None = None  # a directory holding the three codecs (upper, lower, face)
    temperature: float = 0.9
    top_p_temporal: float = 0.8
    top_p_depth: float = 0.95
    cfg_scale: float = 1.3  # guided = null + c * (cond - null); 1.0 switches guidance off
    # added to the logit of the previous step's token at each of `hold_levels` (not in the reference; 0: off)
    hold_bias: float = 0.0
    hold_levels: tuple[int, ...] = ()
    speaker: int = 3
    # weights of the step path (LM, codec decoders): "float32" is exact to training; "bfloat16" (codecs float16)
    # and "int8" (per-row int8 weights everywhere, the fastest; see bench.gesture_step) trade a little precision
    dtype: Literal["float32", "bfloat16", "int8"] = "bfloat16"
    # when this CPU cannot run `dtype`'s fast kernel (gesture.nn.weights): true logs one line and runs the portable
    # kernel (slower); false stops at start-up with that line
    dtype_fallback: bool = True
    warmup_steps: int = 4  # silent steps run at start-up, then the state is reset
    initial_translation: tuple[float, float, float] = (0.0, 1.3, 0.0)
    dialogue_spec: ConditionSpec | None = None  # checked against the LM checkpoint's spec at start-up
    idle: IdleGateConfig = field(default_factory=IdleGateConfig)
    micro_motion: MicroMotionConfig = field(default_factory=MicroMotionConfig)
    face: FaceLayerConfig = field(default_factory=FaceLayerConfig)
    foot_lock: FootLockConfig = field(default_factory=FootLockConfig)
    stabilizer: StabilizerConfig = field(default_factory=StabilizerConfig)
    alternation_filter: AlternationFilterConfig = field(default_factory=AlternationFilterConfig)

    def __post_init__(self) -> None:
        if self.temperature <= 0:
            raise ConfigError(f"gesture.temperature: must be > 0, got {self.temperature}")
        for name in ("top_p_temporal", "top_p_depth"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ConfigError(f"gesture.{name}: must be in (0, 1], got {getattr(self, name)}")
        if self.cfg_scale < 0:
            raise ConfigError(f"gesture.cfg_scale: must be >= 0, got {self.cfg_scale}")
        if self.hold_bias < 0:
            raise ConfigError(f"gesture.hold_bias: must be >= 0, got {self.hold_bias}")
        if any(level < 0 for level in self.hold_levels):
            raise ConfigError(f"gesture.hold_levels: must be token levels >= 0, got {list(self.hold_levels)}")
        if self.speaker < 0:
            raise ConfigError(f"gesture.speaker: must be >= 0, got {self.speaker}")
        if self.warmup_steps < 0:
            raise ConfigError(f"gesture.warmup_steps: must be >= 0, got {self.warmup_steps}")
