"""The gesture stage: dialogue.step -> gesture.step (2 frames of SMPL-X parameters, 20 tokens, voice activity).

`create_component(cfg, run)` loads the LM and the three codecs, checks the LM's condition spec against the
dialogue backend's (`gesture.dialogue_spec`, filled in by the launcher), warms up, and returns the component.
A new session resets the generator. `close()` writes `gesture.json` (step count and step-time percentiles) and, in
offline runs, `motion.npz`: every generated step in BEAT2's layout (poses (2T, 165), trans (2T, 3), expressions
(2T, 100), mocap_frame_rate 25) plus tokens (T, 20) and va_prob (T,), so `python -m render.play`,
`ecas evaluate --motion` and the data tools read it like a BEAT2 take. Live runs keep no record:
nothing in a live session grows with time.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from ecas.core.atomic import atomic_file, write_text_atomic
from ecas.core.component import RunContext
from ecas.core.config import ConfigError
from ecas.core.messages import DialogueStep, GestureStep, Message
from ecas.core.timing import MOTION_FPS, STEP_SAMPLES
from gesture.config import GestureConfig
from gesture.generator import GestureGenerator, level_slices
from gesture.layers import LayerEnv, build_layers
from gesture.lm.checkpoint import load_lm
from gesture.lm.codecs import load_codecs
from gesture.motion_spool import MotionSpool
from gesture.nn.weights import UnsupportedFormError, require_fast_form

log = logging.getLogger(__name__)
STATS_FILE = "gesture.json"
MOTION_FILE = "motion.npz"


class GestureComponent:
    def __init__(self, generator: GestureGenerator, run: RunContext) -> None:
        self.generator = generator
        self.run = run
        self.session: str | None = None
        self.step_ms: list[float] = []  # bounded: summarised and cleared every STATS_EVERY steps
        self.summary = {"steps": 0, "sessions": 0}
        self.record = None if run.live else MotionSpool(run.run_dir / MOTION_FILE)  # on disk: flat memory

    def handle(self, msg: Message) -> Sequence[Message]:
        if not isinstance(msg, DialogueStep):
            return ()
        if msg.session != self.session:
            if self.session is not None:
                self.generator.reset()
            self.session = msg.session
            self.summary["sessions"] += 1
        start = time.perf_counter()
        out = self.generator.step(msg.text_token, msg.agent_codes, msg.agent_pcm)
        self._record((time.perf_counter() - start) * 1e3)
        step = GestureStep(
            poses=out.poses, trans=out.trans, expressions=out.expressions, tokens=out.tokens, va_prob=out.va_prob
        )
        if self.record is not None:
            self.record.append(step)
        return (step,)

    def _record(self, ms: float) -> None:
        self.summary["steps"] += 1
        self.step_ms.append(ms)
        if len(self.step_ms) >= 4096:
            self._summarise()

    def _summarise(self) -> None:
        if self.step_ms:
            ms = np.asarray(self.step_ms)
            self.summary.update(
                step_ms_median=float(np.median(ms)),
                step_ms_p95=float(np.percentile(ms, 95)),
                step_ms_p99=float(np.percentile(ms, 99)),
                step_ms_max=float(ms.max()),
            )
            self.step_ms.clear()

    def flush(self) -> Sequence[Message]:
        return ()

    def close(self) -> None:
        self._summarise()
        self.generator.close()
        self.run.run_dir.mkdir(parents=True, exist_ok=True)
        write_text_atomic(self.run.run_dir / STATS_FILE, json.dumps(self.summary, indent=2))
        if self.record is not None:
            self.record.close(MOTION_FPS)

    def partial_files(self) -> list[Path]:
        return self.record.partial_files() if self.record is not None else []


def write_motion(path: Path, steps: Sequence[GestureStep]) -> None:
    """The generated steps as one npz (see the module docstring), written atomically (ecas.core.atomic)."""
    poses = np.concatenate([s.poses for s in steps])  # (2T, 55, 3)
    with atomic_file(path) as f:
        _savez(f, steps, poses)


def _savez(f, steps: Sequence[GestureStep], poses: np.ndarray) -> None:
    np.savez(
        f,
        poses=poses.reshape(len(poses), -1),
        trans=np.concatenate([s.trans for s in steps]),
        expressions=np.concatenate([s.expressions for s in steps]),
        mocap_frame_rate=np.float32(MOTION_FPS),
        tokens=np.stack([s.tokens for s in steps]),
        va_prob=np.array([s.va_prob for s in steps], np.float32),
    )


def build_generator(cfg: GestureConfig, seed: int) -> GestureGenerator:
    """The generator of a `gesture:` section: checkpoints, spec check, sampling options, runtime layers."""
    if cfg.lm_checkpoint is None:
        raise ConfigError("gesture.lm_checkpoint: required (a directory written by ecas train-lm)")
    if cfg.codec_checkpoints is None:
        raise ConfigError("gesture.codec_checkpoints: required (a directory with upper/, lower/ and face/ codecs)")
    try:
        require_fast_form(cfg.dtype, "gesture.dtype", cfg.dtype_fallback, "gesture.dtype_fallback")
    except UnsupportedFormError as error:
        raise ConfigError(str(error)) from None
    lm = load_lm(cfg.lm_checkpoint, cfg.dialogue_spec)
    codecs = load_codecs(cfg.codec_checkpoints)
    layers = build_layers(cfg.layers, LayerEnv(seed=seed, fps=MOTION_FPS, levels=level_slices(lm)))
    return GestureGenerator(
        lm,
        codecs,
        temperature=cfg.temperature,
        top_p_temporal=cfg.top_p_temporal,
        top_p_depth=cfg.top_p_depth,
        cfg_scale=cfg.cfg_scale,
        speaker=cfg.speaker,
        seed=seed,
        dtype=cfg.dtype,
        hold_bias=cfg.hold_bias,
        hold_levels=cfg.hold_levels,
        layers=layers,
        speaking_rms=cfg.speaking_rms,
        initial_translation=cfg.initial_translation,
    )


def warm_up(generator: GestureGenerator, steps: int) -> None:
    """Run `steps` silent steps (no condition), then reset: first-call allocations happen before the stream."""
    silence = np.zeros(STEP_SAMPLES, np.float32)
    for _ in range(steps):
        generator.step(-1, np.full(generator.spec.n_audio_codebooks, -1), silence)
    generator.reset()


def create_component(cfg: GestureConfig, run: RunContext) -> GestureComponent:
    torch.set_num_threads(1)
    generator = build_generator(cfg, run.seed)
    warm_up(generator, cfg.warmup_steps)
    log.info(
        "gesture LM %s (spec %s), codecs %s, cfg %.2f, dtype %s",
        cfg.lm_checkpoint,
        generator.spec.name,
        cfg.codec_checkpoints,
        cfg.cfg_scale,
        cfg.dtype,
    )
    return GestureComponent(generator, run)
