"""The playback backend: the agent speaks a recording with text tokens from a transcript or from ASR."""

from pathlib import Path

import numpy as np
import pytest

from dialogue.config import ConfigError
from dialogue.text_vocab import word_token
from ecas.core.audio_file import load_audio
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES
from tests.dialogue_helpers import BEAT2_WAV, LIBRIVOX, dialogue_cfg, load_24k, run_component, silence

DATA = Path(__file__).parent / "data" / "dialogue"
STEP_S = STEP_SAMPLES / SAMPLE_RATE_HZ
REFERENCE = LIBRIVOX.with_suffix(".txt").read_text().lower().split()


def playback_cfg(transcript=None, **playback):
    return dialogue_cfg(backend="playback", playback={"speak": str(LIBRIVOX), "transcript": transcript, **playback})


def spoken_words(steps):
    return [(i, s.text_piece) for i, s in enumerate(steps) if s.text_token >= 0]


@pytest.mark.parametrize("transcript", ["librivox_0870.whisper.json", "librivox_0870.TextGrid", "plain"])
def test_text_tokens_follow_the_transcript(transcript, tmp_path):
    path = str(LIBRIVOX.with_suffix(".txt")) if transcript == "plain" else str(DATA / transcript)
    steps, doc = run_component(playback_cfg(path), silence(8.0), tmp_path)
    recording = load_audio(LIBRIVOX, SAMPLE_RATE_HZ)
    np.testing.assert_array_equal(steps[0].agent_pcm, recording[:STEP_SAMPLES])
    words = spoken_words(steps)
    assert [w for _, w in words] == REFERENCE  # every transcript word, in order ("mister" etc. as written)
    (agent,) = [t for t in doc["turns"] if t["speaker"] == "agent"]
    for (step, piece), word in zip(words, agent["words"]):
        assert steps[step].text_token == word_token(piece)
        assert step - 1 <= word["start_s"] / STEP_S < step + 3  # at its start step (a few queue behind a burst)


@pytest.mark.slow
def test_without_transcript_words_come_from_recognition(tmp_path):
    steps, _ = run_component(playback_cfg(), silence(8.0), tmp_path)
    words = [w for _, w in spoken_words(steps)]
    assert len(set(words) & set(REFERENCE)) >= 0.5 * len(set(REFERENCE))


def test_the_user_is_still_heard_while_the_agent_plays(tmp_path):
    user = np.concatenate([silence(1.0), load_24k(BEAT2_WAV)[: 5 * SAMPLE_RATE_HZ], silence(2.0)])
    steps, doc = run_component(playback_cfg(str(DATA / "librivox_0870.whisper.json"), start_s=0.5), user, tmp_path)
    assert not steps[0].agent_speaking and steps[7].agent_speaking  # starts at 0.5 s
    user_turns = [t for t in doc["turns"] if t["speaker"] == "user"]
    assert user_turns and len(user_turns[0]["words"]) >= 5
    assert len({tuple(s.user_codes) for s in steps[13:75]}) > 30
    assert not any(s.agent_interrupted for s in steps)


def test_playback_needs_a_recording():
    with pytest.raises(ConfigError, match="dialogue.playback.speak"):
        dialogue_cfg(backend="playback")
