"""The dialogue stage: audio.user -> dialogue.step, and the run's transcript.json."""

import logging
from collections.abc import Sequence

import torch

from dialogue.backend import DialogueBackend, build_backend
from dialogue.config import DialogueConfig
from ecas.core.component import RunContext
from ecas.core.messages import AudioUser, Message

log = logging.getLogger(__name__)
TRANSCRIPT_EVERY_STEPS = 25  # rewrite transcript.json about every 2 s, so a crash still leaves one


class DialogueComponent:
    def __init__(self, backend: DialogueBackend, transcript_path):
        self.backend = backend
        self.transcript_path = transcript_path
        self._steps = 0
        self._last_step = -1  # the source numbers its steps from 0

    @property
    def spec(self):
        return self.backend.spec

    def handle(self, msg: Message) -> Sequence[Message]:
        if not isinstance(msg, AudioUser):
            return ()
        if msg.step > self._last_step + 1:
            self.backend.skip(msg.step - self._last_step - 1)  # steps dropped upstream (live mode)
        self._last_step = msg.step
        out = self.backend.step(msg.pcm)
        self._steps += 1
        if self._steps % TRANSCRIPT_EVERY_STEPS == 0:
            self.backend.transcript.write(self.transcript_path)
        return (out,)

    def flush(self) -> Sequence[Message]:
        self.backend.transcript.write(self.transcript_path)
        return ()

    def close(self) -> None:
        self.backend.close()
        self.backend.transcript.write(self.transcript_path)


def create_component(cfg: DialogueConfig, run: RunContext) -> DialogueComponent:
    torch.set_num_threads(1)
    backend = build_backend(cfg, seed=run.seed)
    run.run_dir.mkdir(parents=True, exist_ok=True)
    log.info("dialogue backend %s, condition spec %s", cfg.backend, backend.spec)
    return DialogueComponent(backend, run.run_dir / cfg.transcript_name)
