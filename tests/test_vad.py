"""Voice activity: the turn state machine, Silero on real speech, and the streaming resampler."""

import numpy as np
import pytest

from dialogue.config import ConfigError
from dialogue.resample import StreamResampler
from dialogue.vad import VAD_CHUNK_S, SileroVad, VadStateMachine
from ecas.core.messages import VadState
from tests.dialogue_helpers import LIBRIVOX, dialogue_cfg, load_24k


def drive(machine, probs):
    states, events = [], []
    for p in probs:
        e = machine.update(p)
        states.append(machine.state)
        if e:
            events.append(e)
    return states, events


def test_state_machine_walks_quiet_starting_speaking_stopping_quiet():
    m = VadStateMachine(start_threshold=0.5, stop_threshold=0.3, start_s=0.096, stop_s=0.192)  # 3 and 6 chunks
    states, events = drive(m, [0.0, 0.9, 0.9, 0.9, 0.9, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.0])
    assert states[:5] == [VadState.QUIET, VadState.STARTING, VadState.STARTING, VadState.SPEAKING, VadState.SPEAKING]
    assert states[5:10] == [VadState.STOPPING] * 5 and states[10] == VadState.QUIET
    assert [e.kind for e in events] == ["start", "end"]
    assert events[0].t_s == pytest.approx(VAD_CHUNK_S)  # speech began at the second chunk
    assert events[1].t_s == pytest.approx(5 * VAD_CHUNK_S)  # silence began at the sixth


def test_short_blips_and_pauses_do_not_change_the_turn():
    m = VadStateMachine(0.5, 0.3, start_s=0.096, stop_s=0.192)
    states, events = drive(m, [0.9, 0.1, 0.0])  # a 32 ms blip
    assert events == [] and states[-1] == VadState.QUIET
    states, events = drive(m, [0.9] * 4 + [0.1] * 3 + [0.9] * 2)  # a 96 ms pause inside speech
    assert [e.kind for e in events] == ["start"] and states[-1] == VadState.SPEAKING
    states, _ = drive(m, [0.4] * 20)  # between the thresholds: hold
    assert set(states) == {VadState.SPEAKING}


def test_silero_hears_real_speech_not_silence():
    vad = SileroVad()
    speech16k = StreamResampler(24_000, 16_000).process(load_24k(LIBRIVOX))
    probs = vad.process(speech16k)
    assert len(probs) == len(speech16k) // 512
    assert np.mean(np.array(probs) > 0.5) > 0.6
    vad.reset()
    assert max(vad.process(np.zeros(16_000, np.float32))) < 0.1


def test_silero_carries_the_remainder_across_blocks():
    speech16k = StreamResampler(24_000, 16_000).process(load_24k(LIBRIVOX))[:16_000]
    whole = SileroVad().process(speech16k)
    vad = SileroVad()
    streamed = [p for i in range(0, len(speech16k), 1280) for p in vad.process(speech16k[i : i + 1280])]
    np.testing.assert_allclose(streamed, whole, atol=1e-6)


def test_streaming_resampler_equals_offline_and_keeps_the_rate():
    x = np.random.default_rng(0).standard_normal(24_000 * 2).astype(np.float32)
    offline = StreamResampler(24_000, 16_000).process(x)
    stream = StreamResampler(24_000, 16_000)
    sizes = [1920] * 10 + [7, 1, 3000] + [1920] * 3
    pieces, start = [], 0
    for n in sizes:
        pieces.append(stream.process(x[start : start + n]))
        start += n
    streamed = np.concatenate(pieces)
    np.testing.assert_allclose(streamed, offline[: len(streamed)], atol=1e-5)
    assert [len(StreamResampler(24_000, 16_000).process(x[:1920]))] == [1280]


def test_streaming_resampler_is_causal():
    x = np.random.default_rng(1).standard_normal(4000).astype(np.float32)
    short = StreamResampler(24_000, 16_000).process(x[:3000])
    longer = StreamResampler(24_000, 16_000).process(x)
    np.testing.assert_array_equal(short, longer[: len(short)])


@pytest.mark.parametrize(
    "section, message",
    [
        ({"vad": {"stop_threshold": 0.9, "start_threshold": 0.5}}, "dialogue.vad.stop_threshold"),
        ({"vad": {"stop_s": 0}}, "dialogue.vad.stop_s"),
        ({"barge_in_s": 0}, "dialogue.barge_in_s"),
        ({"vad": {"hangover": 1}}, "dialogue.vad.hangover: unknown option"),
    ],
)
def test_bad_vad_options_are_named(section, message):
    with pytest.raises(ConfigError, match=message):
        dialogue_cfg(**section)
