"""The public engine (gesture.engine): chunking never changes the motion, appending never changes earlier steps,
it moves as the multi-process gesture stage does for the same recording and seed, other rates and int16 work,
bad input is a clear error, and words and speech move the avatar."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
import torch

from dialogue.alignment import recognize
from dialogue.resample import StreamResampler
from dialogue.speaker import Speaker
from dialogue.transcript import Transcript
from dialogue.tts import Utterance, WordTiming
from ecas.core.audio_file import load_audio
from ecas.core.config import ConfigError
from ecas.core.paths import EXAMPLES_DIR
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES
from gesture.engine import MAX_PENDING_WORDS, Engine, MotionStep, Word, WordTrack

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parents[1]
EXAMPLE = EXAMPLES_DIR / "librivox_0870.wav"  # 16 kHz int16 speech
CLIP_S = 3.0


@pytest.fixture(scope="module")
def engine():
    with Engine.from_config(seed=3) as engine:
        yield engine


@pytest.fixture(scope="module")
def clip():
    """The example's first 3 s at 24 kHz, and the words the playback backend recognises in it."""
    pcm = load_audio(EXAMPLE, SAMPLE_RATE_HZ)[: int(CLIP_S * SAMPLE_RATE_HZ)]
    return pcm, playback_words(pcm)


def playback_words(pcm: np.ndarray) -> list[Word]:
    """The words the playback backend gives a recording without a transcript (dialogue.playback_backend)."""
    found = recognize(pcm, SAMPLE_RATE_HZ)
    return [Word(w.word, w.start_s, w.end_s) for w in found if 0 <= w.start_s * SAMPLE_RATE_HZ < len(pcm)]


def by_steps(engine: Engine, pcm: np.ndarray, words=()) -> list[MotionStep]:
    """80 ms at a time, every word given with the first step, then the partial step flushed."""
    engine.reset()
    n = len(pcm) // STEP_SAMPLES
    out = [engine.step(pcm[i * STEP_SAMPLES : (i + 1) * STEP_SAMPLES], words=words if i == 0 else ()) for i in range(n)]
    out += engine.feed(pcm[n * STEP_SAMPLES :])
    return out + engine.flush()


def assert_same_motion(a: list[MotionStep], b: list[MotionStep]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert (x.step, x.t_audio_s, x.speaking, x.text_token) == (y.step, y.t_audio_s, y.speaking, y.text_token)
        for name in ("poses", "trans", "expressions", "tokens"):
            np.testing.assert_array_equal(getattr(x, name), getattr(y, name), err_msg=f"step {x.step} {name}")


def test_random_chunk_sizes_give_the_motion_of_80_ms_steps(engine, clip):
    pcm, words = clip
    reference = by_steps(engine, pcm, words)
    assert len(reference) == -(-len(pcm) // STEP_SAMPLES)
    assert reference[0].poses.shape == (2, 55, 3) and reference[0].trans.shape == (2, 3)
    assert reference[0].expressions.shape == (2, 100) and reference[0].poses.dtype == np.float32
    rng = np.random.default_rng(0)
    engine.reset()
    chunked, at = [], 0
    while at < len(pcm):
        size = int(rng.integers(1, 3 * STEP_SAMPLES))
        # each word arrives with the chunk that holds its start: some late for their step, none early
        due = [w for w in words if at <= w.start_s * SAMPLE_RATE_HZ < at + size]
        chunked += engine.feed(pcm[at : at + size], words=due)
        at += size
    assert_same_motion(reference, chunked + engine.flush())


def test_appending_audio_never_changes_earlier_steps(engine, clip):
    pcm, words = clip
    full = by_steps(engine, pcm, words)
    engine.reset()
    early = engine.feed(pcm[: len(pcm) // 2], words=words)
    kept = [(s.poses.copy(), s.trans.copy(), s.expressions.copy()) for s in early]
    later = engine.feed(pcm[len(pcm) // 2 :]) + engine.flush()
    assert_same_motion(full, early + later)
    for step, (poses, trans, expressions) in zip(early, kept):
        assert not step.poses.flags.writeable  # a caller cannot change them either
        np.testing.assert_array_equal(step.poses, poses)
        np.testing.assert_array_equal(step.trans, trans)
        np.testing.assert_array_equal(step.expressions, expressions)


def test_the_engine_moves_as_the_gesture_stage_for_the_same_recording_and_seed(clip, tmp_path):
    """`launch.py --speak` (io, the playback dialogue backend and the gesture stage, each its own process) and the
    engine fed the same recording, the playback backend's words and the same seed: the same frames."""
    pcm, words = clip
    wav = tmp_path / "speech.wav"
    sf.write(wav, pcm, SAMPLE_RATE_HZ, subtype="FLOAT")  # both sides read exactly these samples
    report = tmp_path / "run"
    run = [sys.executable, "launch.py", "--speak", str(wav), "--headless", "--seed", "5", "--report", str(report)]
    run += ["--set", "run.stages=[io,dialogue,gesture]"]  # no renderer: the motion is what is compared
    done = subprocess.run(run, cwd=REPO, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    with np.load(report / "motion.npz") as stage:
        stage = {k: stage[k] for k in ("poses", "trans", "expressions", "tokens")}
    n_steps = len(stage["tokens"])
    assert n_steps * STEP_SAMPLES >= len(pcm)  # the stage runs on in silence after the recording
    with Engine.from_config(seed=5) as engine:
        steps = engine.feed(pcm, words=words)
        steps += engine.feed(np.zeros(n_steps * STEP_SAMPLES - len(pcm), np.float32))
    assert len(steps) == n_steps
    np.testing.assert_array_equal(np.stack([s.tokens for s in steps]), stage["tokens"])
    np.testing.assert_array_equal(np.concatenate([s.poses for s in steps]).reshape(-1, 165), stage["poses"])
    np.testing.assert_array_equal(np.concatenate([s.trans for s in steps]), stage["trans"])
    np.testing.assert_array_equal(np.concatenate([s.expressions for s in steps]), stage["expressions"])


def test_16_khz_and_int16_input(engine):
    native, rate = sf.read(EXAMPLE, dtype="int16")  # the example as stored: 16 kHz int16
    native = native[: int(CLIP_S * rate)]
    assert rate == 16_000
    at_24k = StreamResampler(rate, SAMPLE_RATE_HZ).process(native.astype(np.float32) / 32768.0)
    reference = by_steps(engine, at_24k)
    engine.reset()
    chunks = np.array_split(native, 17)  # 16 kHz int16 in uneven chunks
    resampled = [s for chunk in chunks for s in engine.feed(chunk, sample_rate_hz=rate)] + engine.flush()
    assert_same_motion(reference, resampled)
    assert any(s.speaking for s in resampled)
    int16_24k = (np.clip(at_24k, -1, 32767 / 32768) * 32768).astype(np.int16)
    as_float = by_steps(engine, int16_24k.astype(np.float32) / 32768)
    engine.reset()
    assert_same_motion(as_float, engine.feed(int16_24k) + engine.flush())


def test_bad_input_is_a_clear_error_naming_the_argument(engine):
    engine.reset()
    step = np.zeros(STEP_SAMPLES, np.float32)
    cases = [
        (lambda: engine.feed(np.zeros((STEP_SAMPLES, 2), np.float32)), "agent_pcm: expected mono"),
        (lambda: engine.feed(np.full(10, np.nan, np.float32)), "agent_pcm: contains NaN"),
        (lambda: engine.feed(np.zeros(10, np.int32)), "agent_pcm: .*dtype int32"),
        (lambda: engine.feed(step, sample_rate_hz=0), "sample_rate_hz: must be a positive integer, got 0"),
        (lambda: engine.feed(step, user_pcm=np.zeros((4, 2))), "user_pcm: expected mono"),
        (lambda: engine.feed(step, words=[Word("hi", float("nan"), 1.0)]), r"words\[0\]\.start_s"),
        (lambda: engine.feed(step, words=[Word("hi", 1.0, 0.5)]), r"words\[0\]\.end_s"),
        (lambda: engine.feed(step, words=["hi"]), r"words\[0\]: expected a Word"),
        (lambda: engine.step(step[:100]), "agent_pcm: step takes exactly 1920 samples"),
        (lambda: engine.step_conditioned(-1, np.zeros(8), step[:5]), "agent_pcm: a step is 1920 samples"),
        (lambda: engine.step_conditioned(-1, np.zeros(3)), "audio_codes: expected 8 codes"),
    ]
    for call, message in cases:
        with pytest.raises(ValueError, match=message):
            call()
    assert engine.state.step == 0 and engine.state.source is None  # a refused call leaves the session untouched
    engine.feed(step[:100], sample_rate_hz=16_000)
    with pytest.raises(ValueError, match="sample_rate_hz: this session is fed at 16000 Hz, got 24000"):
        engine.feed(step)
    assert engine.feed(step[:0], user_pcm=np.zeros(480, np.int16), sample_rate_hz=48_000) == []  # user audio alone
    assert engine.state.rate_hz == 16_000 and engine.state.filled == 149  # 100 at 16 kHz: (100 - 1) * 1.5 + 1 out
    with pytest.raises(RuntimeError, match="step_conditioned: this session is driven by audio"):
        engine.step_conditioned(-1, np.zeros(8, np.int64))
    engine.reset()
    engine.feed(step[:100])
    with pytest.raises(ValueError, match="step: 100 samples of a partial step"):
        engine.step(step)
    engine.reset()


def test_words_move_the_motion_from_their_step_on_and_speech_is_told_from_silence(engine, clip):
    pcm, words = clip
    silence = np.zeros(2 * STEP_SAMPLES * 12, np.float32)
    with_words = by_steps(engine, np.concatenate([pcm, silence]), words)
    without = by_steps(engine, np.concatenate([pcm, silence]))
    first = next(s.step for s in with_words if s.text_token >= 0)
    assert first == int(round(words[0].start_s * SAMPLE_RATE_HZ)) // STEP_SAMPLES
    assert all(s.text_token == -1 for s in without)
    assert_same_motion(with_words[:first], without[:first])  # causal: nothing changes before the first word
    later = [not np.array_equal(a.tokens, b.tokens) for a, b in zip(with_words[first:], without[first:])]
    assert sum(later) > len(later) // 2
    speech_steps = len(pcm) // STEP_SAMPLES
    assert np.mean([s.speaking for s in with_words[:speech_steps]]) > 0.6
    assert not any(s.speaking for s in with_words[speech_steps + 1 :])


def test_word_tokens_land_on_the_steps_the_dialogue_speaker_gives_them():
    """WordTrack against the real Speaker of the dialogue backends, with crowded words queueing for free steps."""
    rng = np.random.default_rng(1)
    n_steps = 60
    starts = np.sort(rng.integers(0, n_steps * STEP_SAMPLES, 40))
    texts = [f"w{i}" for i in range(len(starts))]
    speaker = Speaker(Transcript("t"))
    pcm = np.full(n_steps * STEP_SAMPLES, 0.1, np.float32)
    speaker.play(Utterance(text=" ".join(texts), pcm=pcm, words=tuple(map(WordTiming, texts, starts.tolist()))))
    expected = [speaker.step(i * 0.08).text_token for i in range(n_steps)]
    track = WordTrack()
    track.add([Word(t, s / SAMPLE_RATE_HZ, s / SAMPLE_RATE_HZ) for t, s in zip(texts, starts)][::-1])
    assert [track.take(i) for i in range(n_steps)] == expected
    with pytest.raises(ValueError, match=f"words: more than {MAX_PENDING_WORDS} words wait"):
        track.add([Word("x", 100.0, 100.0)] * (MAX_PENDING_WORDS + 1))


def test_the_package_exports_the_engine_lazily():
    code = (
        "import sys, ecas.core.timing, ecas\n"
        "assert 'gesture.engine' not in sys.modules and 'torch' not in sys.modules, 'eager import'\n"
        "from ecas import Engine, MotionStep, Word\n"
        "import gesture.engine as e\n"
        "assert (Engine, MotionStep, Word) == (e.Engine, e.MotionStep, e.Word)\n"
        "assert 'Engine' in dir(ecas)\n"
    )
    subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True)
    import ecas

    with pytest.raises(AttributeError, match="no attribute 'Motion'"):
        ecas.Motion  # noqa: B018


def test_the_packaged_config_is_found_from_any_directory_and_overrides_are_checked(tmp_path):
    code = (
        "import numpy as np\n"
        "from ecas import Engine\n"
        "with Engine.from_config(overrides=['gesture.speaker=0']) as engine:\n"
        "    assert engine.step(np.zeros(1920, np.float32)).poses.shape == (2, 55, 3)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, check=True)
    with pytest.raises(ConfigError, match="gesture.cfg_scal: unknown option"):
        Engine.from_config(overrides=["gesture.cfg_scal=1.0"])
    with pytest.raises(ConfigError, match="config file not found"):
        Engine.from_config(tmp_path / "missing.yaml")
