"""End of turn on real speech: the smart-turn features, its streaming ring, and the agent waiting through pauses.

The cases are assembled from real recordings by bench.dialogue (also written as WAVs for launch.py --replay):
librivox's sentence split in two by a 1.5 s pause (after "how much", where the reader takes a breath), and two of
the BEAT2 speaker's sentences whose pause is lengthened to 1.5 s, with the recording's own background.
"""

import numpy as np
import pytest
import soundfile as sf
from scipy.signal import resample_poly

from bench.dialogue import LIBRIVOX_BREATH_S, PAUSE_S, split_sentence, two_sentences
from dialogue.config import ConfigError, EchoConfig, TurnConfig, VadConfig
from dialogue.end_of_turn import N_FRAMES, N_MELS, RATE_HZ, WINDOW_SAMPLES, EndOfTurnState, SmartTurn, log_mel
from dialogue.listener import UserListener
from ecas.core.messages import VadState
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_S
from tests.dialogue_helpers import BEAT2_WAV, LIBRIVOX, blocks, dialogue_cfg, load_24k, run_component, silence

ANSWER_WITHIN_S = 1.0
TAIL_S = 5.0


def at_24k(case) -> tuple[np.ndarray, float]:
    """A case of bench.dialogue as the user's 24 kHz audio, and where its pause starts."""
    pcm, rate, pause_start_s = case()
    return resample_poly(pcm, SAMPLE_RATE_HZ, rate).astype(np.float32), pause_start_s


def load_16k(path) -> np.ndarray:
    pcm, rate = sf.read(str(path), dtype="float32", always_2d=True)
    return resample_poly(pcm.mean(1), RATE_HZ, rate).astype(np.float32)


def speech_end_s(pcm: np.ndarray, floor_dbfs: float = -35.0) -> float:
    """End of the last 20 ms frame louder than floor_dbfs: where the user's last word ends."""
    frame = SAMPLE_RATE_HZ // 50
    rms = np.sqrt(np.mean(pcm[: len(pcm) // frame * frame].reshape(-1, frame) ** 2, axis=1))  # (frames,)
    return (int(np.flatnonzero(20 * np.log10(rms + 1e-12) > floor_dbfs)[-1]) + 1) * frame / SAMPLE_RATE_HZ


def agent_starts(transcript: dict) -> list[float]:
    return [t["start_s"] for t in transcript["turns"] if t["speaker"] == "agent"]


# --- features and the model ------------------------------------------------------------------------------------


def real_windows() -> list[np.ndarray]:
    """8 s windows of real speech ending at several points, left-padded with zeros when shorter."""
    out = []
    for pcm in (load_16k(LIBRIVOX), load_16k(BEAT2_WAV)[: 30 * RATE_HZ]):
        for end in np.linspace(RATE_HZ, len(pcm), 4).astype(int):
            seg = pcm[max(0, end - WINDOW_SAMPLES) : end]
            out.append(np.pad(seg, (WINDOW_SAMPLES - len(seg), 0)))
    return out


def test_log_mel_equals_whisper_feature_extractor():
    transformers = pytest.importorskip("transformers")
    extractor = transformers.WhisperFeatureExtractor(chunk_length=8)
    for window in real_windows():
        ref = extractor(
            window,
            sampling_rate=RATE_HZ,
            padding="max_length",
            max_length=WINDOW_SAMPLES,
            truncation=True,
            do_normalize=True,
            return_tensors="np",
        ).input_features[0]
        ours = log_mel(window)
        assert ours.shape == ref.shape == (N_MELS, N_FRAMES)
        np.testing.assert_allclose(ours, ref, atol=1e-4)


def test_log_mel_is_bounded_and_rejects_a_wrong_length():
    features = log_mel(real_windows()[1])
    assert features.dtype == np.float32 and features.shape == (N_MELS, N_FRAMES)
    assert features.max() - features.min() <= 2.0 + 1e-6  # 8 log10 units below the loudest, / 4
    with pytest.raises(ValueError, match="128000"):
        log_mel(np.zeros(16_000, np.float32))


def test_ring_keeps_the_last_8_s_in_any_block_sizes_without_growing():
    pcm = load_16k(BEAT2_WAV)[: 20 * RATE_HZ]
    state = EndOfTurnState.empty()
    ring, window = state.ring, state.window
    rng = np.random.default_rng(0)
    i = 0
    while i < len(pcm):
        n = int(rng.integers(1, 3000))
        state.push(pcm[i : i + n])
        i += n
    assert state.ring is ring and state.window is window and ring.shape == (WINDOW_SAMPLES,)
    np.testing.assert_array_equal(state.recent(8.0), pcm[-WINDOW_SAMPLES:])
    recent = state.recent(2.0)
    np.testing.assert_array_equal(recent[-2 * RATE_HZ :], pcm[-2 * RATE_HZ :])
    assert not recent[: -2 * RATE_HZ].any()
    state.push(pcm[: 10 * RATE_HZ])  # a block longer than the ring keeps its own last 8 s
    np.testing.assert_array_equal(state.recent(8.0), pcm[2 * RATE_HZ : 10 * RATE_HZ])
    state.reset()
    assert not state.recent(8.0).any() and state.write == 0


def test_the_model_hears_a_finished_sentence_from_a_breath():
    model = SmartTurn(threshold=0.5)
    pcm = load_16k(LIBRIVOX)
    breath = int(LIBRIVOX_BREATH_S * RATE_HZ)
    model.step(pcm[:breath])
    model.step(np.zeros(RATE_HZ // 5, np.float32))  # the 0.2 s of silence after which it is asked
    assert not model.is_complete(breath / RATE_HZ) and model.state.last_probability < 0.1
    model.reset()
    model.step(pcm)
    model.step(np.zeros(RATE_HZ // 5, np.float32))
    assert model.is_complete(len(pcm) / RATE_HZ) and model.state.last_probability > 0.9
    assert model.state.calls == 1


def test_a_missing_model_file_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="smart-turn model not found"):
        SmartTurn(0.5, tmp_path / "none.onnx")


@pytest.mark.parametrize(
    "section, key",
    [
        ({"threshold": 1.0}, "turn.threshold"),
        ({"min_wait_s": 0.0}, "turn.min_wait_s"),
        ({"min_wait_s": 0.5, "max_wait_s": 0.3}, "turn.max_wait_s"),
        ({"max_wait_s": 11.0}, "turn.max_wait_s"),
        ({"detector": "psychic"}, "turn.detector"),
    ],
)
def test_bad_turn_options_name_the_option(section, key):
    with pytest.raises(ConfigError, match=key):
        dialogue_cfg(turn=section)


def test_turn_defaults():
    assert TurnConfig().detector == "smart_turn" and dialogue_cfg().turn == TurnConfig()


# --- the agent on real speech ----------------------------------------------------------------------------------


@pytest.mark.parametrize("case", [split_sentence, two_sentences], ids=["split_sentence", "two_sentences"])
def test_the_agent_waits_through_a_pause_and_answers_the_end(case, tmp_path):
    pcm, pause_start_s = at_24k(case)
    end_s = speech_end_s(pcm)
    steps, transcript = run_component(
        dialogue_cfg(turn={"detector": "smart_turn"}), np.concatenate([pcm, silence(TAIL_S)]), tmp_path
    )
    starts = agent_starts(transcript)
    assert starts, "the agent never answered"
    assert min(starts) >= end_s, f"the agent started at {min(starts):.2f} s, inside the user's turn (end {end_s:.2f})"
    assert min(starts) - end_s <= ANSWER_WITHIN_S
    user = [t for t in transcript["turns"] if t["speaker"] == "user"]
    assert len(user) == 1 and user[0]["start_s"] < pause_start_s < user[0]["end_s"]  # one turn across the pause
    # While the user pauses the agent listens: no reply, no agent text, the turn still the user's.
    pause = steps[int(pause_start_s / STEP_S) + 4 : int((pause_start_s + PAUSE_S) / STEP_S) - 1]
    assert pause and all(not s.agent_speaking and not s.agent_pcm.any() and not s.text_piece for s in pause)
    assert not any(s.user_words for s in pause)  # no user turn was handed to the responder
    assert {s.user_vad_state for s in pause} <= {VadState.STOPPING, VadState.SPEAKING}


def test_silence_detection_answers_into_the_pause(tmp_path):
    """Today's behaviour, kept by detector "silence": the agent starts inside the user's 1.5 s pause."""
    pcm, pause_start_s = at_24k(split_sentence)
    _, transcript = run_component(
        dialogue_cfg(turn={"detector": "silence"}), np.concatenate([pcm, silence(TAIL_S)]), tmp_path
    )
    assert pause_start_s < min(agent_starts(transcript)) < pause_start_s + PAUSE_S


def test_the_turn_ends_after_the_longest_wait_when_the_model_hears_no_end(tmp_path):
    """The user stops after "how much" and says nothing more: the agent answers after max_wait_s of silence."""
    pcm = load_24k(LIBRIVOX)[: int(LIBRIVOX_BREATH_S * SAMPLE_RATE_HZ)]
    end_s = speech_end_s(pcm)
    max_wait_s = 1.5
    _, transcript = run_component(
        dialogue_cfg(turn={"detector": "smart_turn", "max_wait_s": max_wait_s}),
        np.concatenate([pcm, silence(TAIL_S)]),
        tmp_path,
    )
    (start_s,) = agent_starts(transcript)
    assert max_wait_s <= start_s - end_s <= max_wait_s + ANSWER_WITHIN_S


def test_the_listener_asks_the_model_once_per_pause_and_keeps_one_turn():
    """Without recognition: one turn across the 1.5 s pause, the model asked at the pause and at the end."""
    pcm, pause_start_s = at_24k(split_sentence)
    end_s = speech_end_s(pcm)
    turn = TurnConfig(detector="smart_turn")
    listener = UserListener(VadConfig(), EchoConfig(), None, turn)
    events = [e for block in blocks(np.concatenate([pcm, silence(3.0)])) for e in listener.step(block, None).events]
    model = listener.turns.end_of_turn
    assert [e.kind for e in events] == ["start", "end"] and events[0].t_s < pause_start_s
    assert end_s - 0.1 < events[1].t_s < end_s + 0.2  # the turn ends where the speech does
    assert model.state.calls == 2 and model.state.last_probability >= turn.threshold
