"""The io stage: the user's audio in (replay or microphone), the agent's voice out (optional speaker)."""

from __future__ import annotations

from collections.abc import Sequence

from agent.io.sources import MicSource, ReplaySource
from agent.io.speaker import Speaker
from agent.sections import IoConfig
from ecas.core.component import RunContext
from ecas.core.messages import DialogueStep, Message


class IoComponent:
    """Receives the agent's steps and plays them when a speaker is configured."""

    def __init__(self, speaker: Speaker | None):
        self.speaker = speaker

    def handle(self, msg: Message) -> Sequence[Message]:
        if self.speaker is not None and isinstance(msg, DialogueStep):
            self.speaker.play(msg.agent_pcm)
        return ()

    def flush(self) -> Sequence[Message]:
        return ()

    def close(self) -> None:
        if self.speaker is not None:
            self.speaker.close()

    def counters(self) -> dict[str, int]:
        return {"speaker_dropped_samples": self.speaker.dropped_samples} if self.speaker else {}


def create_component(cfg: IoConfig, run: RunContext):
    if cfg.source == "mic":
        source = MicSource(cfg.input_device)
    elif cfg.source == "silence":
        source = ReplaySource.silence(cfg.silence_s)
    else:
        source = ReplaySource.from_file(cfg.replay_path, cfg.tail_silence_s)
    speaker = Speaker(cfg.output_device) if cfg.speaker and run.live else None
    return IoComponent(speaker), source
