"""The gesture stage: dialogue.step -> gesture.step (2 frames of SMPL-X parameters, 20 tokens, voice activity).

`create_component(cfg, run)` builds the engine (`gesture.engine`: the LM, the three codecs, the runtime layers),
which checks the LM's condition spec against the dialogue backend's (`gesture.dialogue_spec`, filled in by the
launcher) and warms up. The component drives it with the dialogue stage's codes; a new session resets it.
`close()` writes `gesture.json` (step count and step-time percentiles) and, in offline runs, `motion.npz`: every
generated step in BEAT2's layout (poses (2T, 165), trans (2T, 3), expressions (2T, 100), mocap_frame_rate 25) plus
tokens (T, 20) and va_prob (T,), so `python -m render.play`, `ecas evaluate --motion` and the data tools read it
like a BEAT2 take. Live runs keep no record: nothing in a live session grows with time.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ecas.core.atomic import atomic_file, write_text_atomic
from ecas.core.component import RunContext
from ecas.core.messages import DialogueStep, GestureStep, Message
from ecas.core.timing import MOTION_FPS
from gesture.build import build_generator  # noqa: F401 (re-exported: its old home)
from gesture.config import GestureConfig
from gesture.engine import Engine, MotionStep
from gesture.motion_spool import MotionSpool

log = logging.getLogger(__name__)
STATS_FILE = "gesture.json"
MOTION_FILE = "motion.npz"


class GestureComponent:
    """Drives the engine with the dialogue stage's conditioning (`Engine.step_conditioned`): `--speak`, the live
    loop and user code run one path."""

    def __init__(self, engine: Engine, run: RunContext) -> None:
        self.engine = engine
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
                self.engine.reset()
            self.session = msg.session
            self.summary["sessions"] += 1
        start = time.perf_counter()
        out = self.engine.step_conditioned(msg.text_token, msg.agent_codes, msg.agent_pcm, speaking=msg.agent_speaking)
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
        self.engine.close()
        self.run.run_dir.mkdir(parents=True, exist_ok=True)
        write_text_atomic(self.run.run_dir / STATS_FILE, json.dumps(self.summary, indent=2))
        if self.record is not None:
            self.record.close(MOTION_FPS)

    def partial_files(self) -> list[Path]:
        return self.record.partial_files() if self.record is not None else []


def write_motion(path: Path, steps: Sequence[GestureStep | MotionStep]) -> None:
    """The generated steps (the stage's messages or the engine's steps) as one npz (see the module docstring),
    written atomically (ecas.core.atomic)."""
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


def create_component(cfg: GestureConfig, run: RunContext) -> GestureComponent:
    engine = Engine.from_sections(cfg, seed=run.seed, conditioner=False)  # the dialogue stage sends the codes
    log.info(
        "gesture LM %s (spec %s), codecs %s, cfg %.2f, dtype %s",
        cfg.lm_checkpoint,
        engine.spec.name,
        cfg.codec_checkpoints,
        cfg.cfg_scale,
        cfg.dtype,
    )
    return GestureComponent(engine, run)
