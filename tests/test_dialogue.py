"""The dialogue component on replayed real speech: recognition, answers, barge-in, echo, and bad input."""

import numpy as np
import pytest

from dialogue.text_vocab import LOCAL_SPEC, word_token
from ecas.core.messages import DialogueStep, VadState
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES
from tests.dialogue_helpers import BEAT2_WAV, LIBRIVOX, blocks, dialogue_cfg, load_24k, run_component, silence

STEP_S = STEP_SAMPLES / SAMPLE_RATE_HZ


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def reference_words() -> set[str]:
    return set(LIBRIVOX.with_suffix(".txt").read_text().lower().split())


def turns(transcript, speaker):
    return [t for t in transcript["turns"] if t["speaker"] == speaker]


@pytest.fixture(scope="module")
def librivox_run(tmp_path_factory):
    pcm = np.concatenate([load_24k(LIBRIVOX), silence(3.0)])
    return run_component(dialogue_cfg(), pcm, tmp_path_factory.mktemp("librivox"))


def test_user_words_are_recognised_with_times(librivox_run):
    steps, transcript = librivox_run
    (user,) = turns(transcript, "user")
    heard = [w["word"] for w in user["words"]]
    assert len(set(heard) & reference_words()) >= 0.5 * len(reference_words())
    starts = [w["start_s"] for w in user["words"]]
    assert starts == sorted(starts) and 0.0 <= starts[0] < 1.0 and user["words"][-1]["end_s"] <= 7.3
    assert user["answered"] is True
    assert any(s.user_words for s in steps) and any(s.user_partial for s in steps)
    states = [s.user_vad_state for s in steps]
    changes = [state for i, state in enumerate(states) if i == 0 or state != states[i - 1]]
    assert changes[0] == VadState.QUIET and changes[-1] == VadState.QUIET
    assert VadState.SPEAKING in changes and VadState.STOPPING in changes
    assert max(s.user_vad_prob for s in steps) > 0.9 and steps[-1].user_vad_prob < 0.1


def test_agent_answers_with_audible_speech_and_aligned_text_tokens(librivox_run):
    steps, transcript = librivox_run
    (agent,) = turns(transcript, "agent")
    user_end = turns(transcript, "user")[0]["end_s"]
    assert user_end < agent["start_s"] < user_end + 1.5
    speaking = [s for s in steps if s.agent_speaking]
    assert len(speaking) * STEP_S > 1.0 and max(rms(s.agent_pcm) for s in speaking) > 0.05
    token_steps = [i for i, s in enumerate(steps) if s.text_token >= 0]
    assert [steps[i].text_piece for i in token_steps] == [w["word"] for w in agent["words"]]
    for i in token_steps:  # the token sits at the step where its word starts: the agent is audible there
        assert steps[i].text_token == word_token(steps[i].text_piece) < LOCAL_SPEC.text_vocab
        assert max(rms(steps[j].agent_pcm) for j in (i, min(i + 1, len(steps) - 1))) > 0.01
        word = agent["words"][token_steps.index(i)]
        assert abs(word["start_s"] - i * STEP_S) <= STEP_S * 2


def test_speech_codes_for_both_sides(librivox_run):
    steps, _ = librivox_run
    for s in steps:
        assert isinstance(s, DialogueStep)
        for codes in (s.agent_codes, s.user_codes):
            assert codes.shape == (8,) and ((codes >= 0) & (codes < LOCAL_SPEC.audio_card)).all()
    user_codes = {tuple(s.user_codes) for s in steps[:80]}
    agent_codes = {tuple(s.agent_codes) for s in steps if s.agent_speaking}
    assert len(user_codes) > 40 and len(agent_codes) > 10  # speech gives varied codes


def test_barge_in_cuts_the_agent_and_the_user_is_answered(tmp_path):
    """The user speaks again 2.3 s after finishing, over the agent's answer; the agent stops and answers."""
    speech = load_24k(LIBRIVOX)
    # The user comes in 1.5 s after their turn ended: inside the agent's reply (which starts 0.3-0.7 s after it).
    overlap_start = (len(speech) + int(1.5 * SAMPLE_RATE_HZ)) // STEP_SAMPLES * STEP_SAMPLES
    pcm = np.concatenate(
        [
            speech,
            silence((overlap_start - len(speech)) / SAMPLE_RATE_HZ),
            speech[: int(3.0 * SAMPLE_RATE_HZ)],
            silence(4.0),
        ]
    )
    steps, transcript = run_component(dialogue_cfg(barge_in_s=0.3), pcm, tmp_path / "barge")
    cut = [i for i, s in enumerate(steps) if s.agent_interrupted]
    assert len(cut) == 1
    assert steps[cut[0] - 1].agent_speaking  # the agent was talking when the user came in
    onset_step = overlap_start // STEP_SAMPLES
    assert onset_step < cut[0] <= onset_step + int(np.ceil((0.3 + 0.25) / STEP_S)) + 2
    assert not steps[cut[0] + 1].agent_speaking and rms(steps[cut[0] + 1].agent_pcm) == 0.0
    agent_turns = turns(transcript, "agent")
    interrupted = [t for t in agent_turns if t["interrupted"]]
    assert len(interrupted) == 1
    at = interrupted[0]["interrupted_at_word"]
    assert at is not None and at == len(interrupted[0]["words"]) - 1
    assert len(interrupted[0]["words"]) < len(interrupted[0]["text"].split())  # cut before the end
    second_user = [t for t in turns(transcript, "user") if t["start_s"] > interrupted[0]["start_s"]]
    assert second_user and second_user[0]["answered"]
    assert any(t["start_s"] > second_user[0]["end_s"] for t in agent_turns)  # and then answered


def room_impulse_response() -> np.ndarray:
    """Loudspeaker to mic: direct path plus 150 ms of decaying reverberation."""
    n = int(0.15 * SAMPLE_RATE_HZ)
    ir = np.random.default_rng(0).standard_normal(n) * np.exp(-np.arange(n) / 720) * 0.05
    ir[0] = 1.0
    return ir.astype(np.float32)


def converse_with_echo(echo_mode: str, run_dir, user=None, echo_gain=0.5):
    """Loudspeakers: the mic hears the user plus the agent's own output (0.2 s later, reverberated)."""
    from dialogue.process import create_component
    from ecas.core.component import RunContext
    from ecas.core.messages import AudioUser

    comp = create_component(dialogue_cfg(echo={"mode": echo_mode}), RunContext(run_dir, False, 0, "e"))
    user = np.concatenate([load_24k(LIBRIVOX), silence(4.5)]) if user is None else user
    ir, delay = room_impulse_response(), int(0.2 * SAMPLE_RATE_HZ)
    user_blocks = blocks(user)
    echo = np.zeros(len(user_blocks) * STEP_SAMPLES + delay + len(ir) + STEP_SAMPLES, np.float32)
    outs = []
    for i, block in enumerate(user_blocks):
        (out,) = comp.handle(AudioUser(pcm=block + echo_gain * echo[i * STEP_SAMPLES : (i + 1) * STEP_SAMPLES], step=i))
        outs.append(out)
        start = (i + 1) * STEP_SAMPLES + delay  # played from the next step on, heard `delay` later
        echo[start : start + STEP_SAMPLES + len(ir) - 1] += np.convolve(out.agent_pcm, ir)
    comp.close()
    return outs


def test_echo_of_the_agents_own_voice_does_not_barge_in(tmp_path):
    gated = converse_with_echo("gate", tmp_path)
    assert sum(s.agent_speaking for s in gated) * STEP_S > 2.0
    assert not any(s.agent_interrupted for s in gated)


@pytest.mark.slow
def test_the_user_can_still_barge_in_over_a_quieter_echo(tmp_path):
    speech = load_24k(LIBRIVOX)
    # The user comes in 1.5 s after their turn ended: inside the agent's reply (which starts 0.3-0.7 s after it).
    overlap_start = (len(speech) + int(1.5 * SAMPLE_RATE_HZ)) // STEP_SAMPLES * STEP_SAMPLES
    user = np.concatenate(
        [
            speech,
            silence((overlap_start - len(speech)) / SAMPLE_RATE_HZ),
            speech[: int(3.0 * SAMPLE_RATE_HZ)],
            silence(3.0),
        ]
    )
    steps = converse_with_echo("gate", tmp_path, user, echo_gain=0.1)
    cut = [i for i, s in enumerate(steps) if s.agent_interrupted]
    assert len(cut) == 1 and cut[0] > overlap_start // STEP_SAMPLES


@pytest.mark.slow
def test_without_the_echo_gate_the_agent_would_cut_itself_off(tmp_path):
    assert any(s.agent_interrupted for s in converse_with_echo("off", tmp_path))


def test_silence_only_gives_a_quiet_agent(tmp_path):
    steps, transcript = run_component(dialogue_cfg(), silence(4.0), tmp_path)
    assert transcript["turns"] == []
    assert not any(s.agent_speaking or s.user_words or s.agent_interrupted for s in steps)
    assert all(s.user_vad_state == VadState.QUIET for s in steps)


def test_noise_only_is_not_taken_for_speech(tmp_path):
    rng = np.random.default_rng(0)
    noise = (0.05 * rng.standard_normal(int(4.0 * SAMPLE_RATE_HZ))).astype(np.float32)
    steps, transcript = run_component(dialogue_cfg(), noise, tmp_path)
    assert not turns(transcript, "user") and not any(s.agent_speaking for s in steps)
    assert all(s.user_vad_prob < 0.5 for s in steps)


@pytest.mark.parametrize("gain, min_known_words", [(5.0, 8), pytest.param(20.0, 0, marks=pytest.mark.slow)])
def test_clipped_speech_is_still_understood_and_answered(gain, min_known_words, tmp_path):
    """1.4% (x5) and 26% (x20) of the samples clipped."""
    clipped = np.clip(load_24k(LIBRIVOX) * gain, -1.0, 1.0)
    steps, transcript = run_component(dialogue_cfg(), np.concatenate([clipped, silence(3.0)]), tmp_path)
    (user,) = turns(transcript, "user")
    assert len({w["word"] for w in user["words"]} & reference_words()) >= min_known_words
    assert user["words"] and user["answered"]
    assert turns(transcript, "agent") and any(s.agent_speaking for s in steps)


def test_non_finite_and_wrong_sized_input(tmp_path):
    from dialogue.process import create_component
    from ecas.core.component import RunContext
    from ecas.core.messages import AudioUser

    comp = create_component(dialogue_cfg(), RunContext(tmp_path, False, 0, "x"))
    bad = np.full(STEP_SAMPLES, np.nan, np.float32)
    (out,) = comp.handle(AudioUser(pcm=bad))
    assert np.isfinite(out.user_pcm).all() and np.isfinite(out.user_vad_prob)
    with pytest.raises(ValueError, match="1920"):
        comp.backend.step(np.zeros(100, np.float32))
    comp.close()


@pytest.mark.slow
def test_sixty_second_monologue(tmp_path):
    """A minute of continuous real speech: recognised, answered once, transcript stays consistent."""
    speech = load_24k(BEAT2_WAV)[: 60 * SAMPLE_RATE_HZ]
    steps, transcript = run_component(dialogue_cfg(), np.concatenate([speech, silence(4.0)]), tmp_path)
    user = turns(transcript, "user")
    assert sum(len(t["words"]) for t in user) > 60
    assert any(t["answered"] for t in user) and turns(transcript, "agent")
    assert len(steps) == len(blocks(np.concatenate([speech, silence(4.0)])))


def test_dropped_input_steps_keep_transcript_times_true(tmp_path):
    """Live mode may drop audio.user steps: times after the gap still follow the message step numbers."""
    import json

    from dialogue.process import create_component
    from ecas.core.component import RunContext
    from ecas.core.messages import AudioUser

    comp = create_component(dialogue_cfg(), RunContext(tmp_path, True, 0, "live"))
    speech_blocks = blocks(np.concatenate([load_24k(LIBRIVOX), silence(3.0)]))
    gap = 25  # 2 s of input never arrived before the user spoke
    for i, block in enumerate(speech_blocks):
        comp.handle(AudioUser(pcm=block, step=i + gap))
    comp.close()
    (user,) = [t for t in json.loads((tmp_path / "transcript.json").read_text())["turns"] if t["speaker"] == "user"]
    assert 2.0 <= user["words"][0]["start_s"] < 3.0 and user["end_s"] < 2.0 + 7.3
