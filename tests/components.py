"""Small stage components for runtime tests. The shipped program never uses these.

Each is built by a `run.components` factory path, e.g. `--set run.components.render=tests.components:recorder`.
Behaviour is tuned through environment variables, since a factory only receives its section config.
"""

from __future__ import annotations

import json
import os
import signal
import time
from collections.abc import Sequence

import numpy as np

from ecas.core.component import RunContext
from ecas.core.messages import AudioUser, DialogueStep, GestureStep, Message, MsgpackSerializer, RenderFrame
from ecas.core.timing import FRAMES_PER_STEP

# `launch.py` options that put these components in place of the real dialogue, gesture and render stages
TEST_STAGES = [
    "--set",
    "run.components.dialogue=tests.components:echo_dialogue",
    "--set",
    "run.components.gesture=tests.components:wave_gesture",
    "--set",
    "run.components.render=tests.components:recorder",
]

KILL_AT_STEP = "TEST_KILL_AT_STEP"  # the stage's process SIGKILLs itself at this step
CORRUPT_AT_STEP = "TEST_CORRUPT_AT_STEP"  # the dialogue stage sends one truncated frame at this step
RENDER_SLEEP_S = "TEST_RENDER_SLEEP_S"  # the recorder sleeps this long per frame


class _Passive:
    def flush(self) -> Sequence[Message]:
        return ()

    def close(self) -> None:
        pass


def _maybe_die(step: int) -> None:
    if int(os.environ.get(KILL_AT_STEP, -1)) == step:
        os.kill(os.getpid(), signal.SIGKILL)


class EchoDialogue(_Passive):
    """The agent echoes the user's audio; codes are the block's coarse energy levels."""

    def handle(self, msg: Message) -> Sequence[Message]:
        if not isinstance(msg, AudioUser):
            return ()
        _maybe_die(msg.step)
        level = int(np.clip(np.abs(msg.pcm).mean() * 1000, 0, 1000))
        codes = np.full(8, level, np.int32)
        return [
            DialogueStep(
                agent_pcm=msg.pcm.copy(),
                user_pcm=msg.pcm.copy(),
                agent_codes=codes,
                user_codes=codes,
                text_token=msg.step % 7,
                text_piece=f"w{msg.step}",
            )
        ]


class WaveGesture(_Passive):
    """Raises the right arm with the step index: a pose that changes every step."""

    def handle(self, msg: Message) -> Sequence[Message]:
        if not isinstance(msg, DialogueStep):
            return ()
        _maybe_die(msg.step)
        poses = np.zeros((FRAMES_PER_STEP, 55, 3), np.float32)
        poses[:, 17, 2] = np.sin(msg.step * 0.1)
        return [
            GestureStep(
                poses=poses,
                trans=np.zeros((FRAMES_PER_STEP, 3), np.float32),
                expressions=np.zeros((FRAMES_PER_STEP, 100), np.float32),
                tokens=np.full(20, msg.step, np.int32),
                va_prob=0.5,
            )
        ]


class Recorder(_Passive):
    """The last stage: emits tiny frames and writes every received (topic, step) to `received.jsonl`."""

    def __init__(self, run: RunContext):
        self.log = open(run.run_dir / "received.jsonl", "a", buffering=1)
        self.sleep_s = float(os.environ.get(RENDER_SLEEP_S, 0))

    def handle(self, msg: Message) -> Sequence[Message]:
        if isinstance(msg, GestureStep):
            time.sleep(self.sleep_s)
        self.log.write(
            json.dumps(
                {
                    "topic": msg.topic,
                    "step": msg.step,
                    "seq": msg.seq,
                    "t_origin_ns": msg.t_origin_ns,
                    "t_done_ns": time.monotonic_ns(),
                }
            )
            + "\n"
        )
        if not isinstance(msg, GestureStep):
            return ()
        return [
            RenderFrame(frame_index=i, width=4, height=4, image=np.full((4, 4, 3), msg.step % 256, np.uint8))
            for i in range(FRAMES_PER_STEP)
        ]

    def set_origin_offset_ns(self, offset_ns: int) -> None:
        """Recorded as a `clock` row: what the stage runner measured on START (ecas.core.component.ClockAware)."""
        self.log.write(json.dumps({"topic": "clock", "origin_offset_ns": offset_ns}) + "\n")

    def close(self) -> None:
        self.log.close()


def _corrupt_sends_at(step: int) -> None:
    """Make this process's serializer truncate the last buffer of the dialogue step `step`."""
    encode = MsgpackSerializer.encode

    def corrupt(self, msg):
        frames = encode(self, msg)
        if isinstance(msg, DialogueStep) and msg.step == step:
            frames[-1] = bytes(frames[-1])[:-3]
        return frames

    MsgpackSerializer.encode = corrupt


def echo_dialogue(cfg, run: RunContext) -> EchoDialogue:
    if CORRUPT_AT_STEP in os.environ:
        _corrupt_sends_at(int(os.environ[CORRUPT_AT_STEP]))
    return EchoDialogue()


def wave_gesture(cfg, run: RunContext) -> WaveGesture:
    return WaveGesture()


def recorder(cfg, run: RunContext) -> Recorder:
    return Recorder(run)
