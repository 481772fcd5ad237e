"""The shipped default agent: checkpoints load under the default config, match the local backend, and move with
speech; the LM tokenizer's pieces; and (slow) the whole training chain at a tiny size."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
import torch

from agent.sections import load_app_config
from dialogue.speech_tokenizer import DEFAULT_CHECKPOINT, SpeechTokenizer
from dialogue.text_vocab import LOCAL_SPEC, word_token
from ecas.core.paths import CHECKPOINTS_DIR, DEFAULT_CONFIG, data_root
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_HZ, STEP_SAMPLES
from gesture.data.audio import load_audio
from gesture.data.beat2 import Word, find_takes
from gesture.lm.checkpoint import load_lm
from gesture.lm.codecs import load_codecs
from gesture.lm.data import LMDataset
from gesture.lm.tokenize import (
    agent_words,
    place_words,
    tokenize_directory,
    tokenize_take,
    vad_from_frames,
    vad_from_words,
)
from gesture.process import build_generator
from gesture.synth.build import generator_fingerprint

REPO = Path(__file__).resolve().parents[1]
CHECKPOINTS = CHECKPOINTS_DIR
BEAT2 = data_root() / "beat2"
SHIPPED_LIMIT_BYTES = 60 * 1024 * 1024


@pytest.fixture(scope="module")
def generator():
    torch.set_num_threads(1)
    app = load_app_config(DEFAULT_CONFIG)
    cfg = app.gesture
    assert cfg.lm_checkpoint is not None and cfg.codec_checkpoints is not None, (
        "ecas/configs/default.yaml: gesture paths"
    )
    import dataclasses

    cfg = dataclasses.replace(cfg, dialogue_spec=LOCAL_SPEC)
    old = os.getcwd()
    os.chdir(REPO)  # config paths are relative to the project root, as launch.py runs
    try:
        gen = build_generator(cfg, seed=0)
    finally:
        os.chdir(old)
    yield gen
    gen.close()


@pytest.fixture(scope="module")
def speech_condition():
    """50 steps of the real clip's speech as the local backend codes it, with word tokens every few steps."""
    pcm = load_audio(BEAT2 / "2_scott_0_1_1.wav", SAMPLE_RATE_HZ)[2 * SAMPLE_RATE_HZ :][: 50 * STEP_SAMPLES]
    codes = SpeechTokenizer.load(DEFAULT_CHECKPOINT).encode(torch.from_numpy(pcm)[None])[0].numpy()  # (8, 50)
    text = np.full(50, -1)
    words = ["so", "we", "went", "there", "and", "then", "we", "saw", "it", "was", "great", "fun", "today"]
    text[::4] = [word_token(w) for w in words][: len(text[::4])]  # 13 word starts
    return text, codes, pcm


def _run(gen, text, codes, pcm):
    gen.reset()
    steps = [
        gen.step(int(text[t]), codes[:, t], pcm[t * STEP_SAMPLES : (t + 1) * STEP_SAMPLES]) for t in range(len(text))
    ]
    return steps


def test_shipped_checkpoints_fit_the_budget_and_have_model_cards():
    files = [p for p in CHECKPOINTS.rglob("*") if p.is_file()]
    assert sum(p.stat().st_size for p in files) <= SHIPPED_LIMIT_BYTES
    for card in ("codecs/README.md", "gesture_lm/README.md"):
        text = (CHECKPOINTS / card).read_text()
        for section in ("## Data", "## Config", "## Metrics", "## Reproduce", "wall time"):
            assert section.lower() in text.lower(), f"{card} lacks {section}"


def test_lm_spec_is_the_local_backends():
    lm = load_lm(CHECKPOINTS / "gesture_lm", LOCAL_SPEC)
    assert lm.spec == LOCAL_SPEC
    codecs = load_codecs(CHECKPOINTS / "codecs")
    assert [codecs[r].n_q for r in ("upper", "lower", "face")] == [lm.sizes.n_upper, lm.sizes.n_lower, lm.sizes.n_face]


def test_generator_runs_and_motion_follows_speech(generator, speech_condition):
    text, codes, pcm = speech_condition
    speech = _run(generator, text, codes, pcm)
    again = _run(generator, text, codes, pcm)
    silence_codes = SpeechTokenizer.load(DEFAULT_CHECKPOINT).encode(torch.zeros(1, 50 * STEP_SAMPLES))[0].numpy()
    silent = _run(generator, np.full(50, -1), silence_codes, np.zeros(50 * STEP_SAMPLES, np.float32))
    for out in speech:
        assert out.poses.shape == (2, 55, 3) and out.trans.shape == (2, 3) and out.expressions.shape == (2, 100)
        assert np.isfinite(out.poses).all() and np.isfinite(out.trans).all() and np.isfinite(out.expressions).all()
        assert out.tokens.shape == (20,) and 0 <= out.tokens.min() and out.tokens.max() < generator.sizes.card
        assert 0.0 <= out.va_prob <= 1.0
    poses = np.concatenate([o.poses for o in speech])  # (100, 55, 3)
    assert poses.std(axis=0).mean() > 1e-3  # the body moves
    assert all(np.array_equal(a.poses, b.poses) for a, b in zip(speech, again))  # seeded: reproducible
    silent_poses = np.concatenate([o.poses for o in silent])
    assert np.abs(poses - silent_poses).mean() > 1e-3  # speech changes the motion
    tokens_speech = np.stack([o.tokens for o in speech])
    tokens_silent = np.stack([o.tokens for o in silent])
    assert (tokens_speech != tokens_silent).mean() > 0.1


# ---------------------------------------------------------------- tokenizer pieces


def test_place_words_puts_each_word_at_its_first_step_or_the_next_free_one():
    words = [Word("hello", 0.0, 0.3), Word("there", 0.05, 0.2), Word("you", 0.9, 1.0), Word("...", 0.5, 0.6)]
    tokens = place_words(words, 20)
    assert tokens[0] == word_token("hello") and tokens[1] == word_token("there")  # same step: queued, as the speaker
    assert tokens[int(0.9 * STEP_HZ)] == word_token("you")
    assert (tokens >= 0).sum() == 3  # punctuation has no token
    assert place_words([Word("late", 5.0, 5.2)], 20).max() == -1  # beyond the take


def test_vad_per_step_from_frames_and_from_words():
    frames = np.array([0, 0, 0, 1, 1, 1, 0, 0, 0, 0])
    assert vad_from_frames(frames, 6).tolist() == [0, 1, 1, 0, 0, 0]
    assert vad_from_words([Word("a", 0.08, 0.20)], 5).tolist() == [0, 1, 1, 0, 0]


def _dyadic_take(root: Path, seconds: float = 4.0) -> None:
    """A tiny BEAT2-layout session: the real clip's first seconds as the agent, with both speakers' words."""
    data = np.load(BEAT2 / "2_scott_0_1_1.npz")
    n30 = int(seconds * 30)
    for sub in ("smplxflame_25", "wave16k", "whisper_transcription"):
        (root / sub).mkdir(parents=True)
    from gesture.data.beat2 import read_motion
    from gesture.data.chunks import motion_at_fps

    motion = motion_at_fps(read_motion(BEAT2 / "2_scott_0_1_1.npz"), 25)
    n = int(seconds * 25)
    vad = np.zeros(n, np.float32)
    vad[25:75] = 1
    np.savez(
        root / "smplxflame_25" / "1_agent_0_0_0.npz",
        poses=motion.poses[:n].reshape(n, -1),
        trans=motion.trans[:n],
        expressions=motion.expressions[:n],
        betas=data["betas"],
        mocap_frame_rate=25,
        vad=vad,
    )
    pcm, rate = sf.read(BEAT2 / "2_scott_0_1_1.wav", dtype="float32")
    sf.write(root / "wave16k" / "1_agent_0_0_0.wav", pcm[: int(seconds * rate)] * 0.5, rate)
    sf.write(root / "wave16k" / "1_agent_0_0_0_agent.wav", pcm[: int(seconds * rate)], rate)
    words = [
        {"word": "hello", "start": 1.0, "end": 1.3, "speaker": "agent"},
        {"word": "right", "start": 1.02, "end": 1.2, "speaker": "user"},
        {"word": "friend", "start": 1.4, "end": 1.8, "speaker": "agent"},
    ]
    (root / "whisper_transcription" / "1_agent_0_0_0.json").write_text(json.dumps({"segments": [{"words": words}]}))
    (root / "train_test_split.csv").write_text("id,type\n1_agent_0_0_0,train\n")
    assert n30  # the clip is long enough


def test_tokenize_a_dyadic_session(tmp_path):
    _dyadic_take(tmp_path / "data")
    take = find_takes(tmp_path / "data")[0]
    assert [w.word for w in agent_words(take, np.zeros(1))] == ["hello", "friend"]  # only the agent's words
    summary = tokenize_directory(tmp_path / "data", CHECKPOINTS / "codecs", tmp_path / "lm")
    assert summary["takes"] == 1 and summary["steps"] == 50
    with np.load(tmp_path / "lm" / "1_agent_0_0_0.npz") as rec:
        assert rec["gesture_tokens"].shape == (20, 50) and rec["audio_codes"].shape == (8, 50)
        assert rec["text_tokens"][int(1.0 * STEP_HZ)] == word_token("hello")
        assert rec["text_tokens"][int(1.4 * STEP_HZ)] == word_token("friend")
        assert (rec["text_tokens"] >= 0).sum() == 2
        assert rec["vad"].tolist() == [0] * 12 + [1] * 26 + [0] * 12  # frames 25..74 at 25 fps
        codes = (
            SpeechTokenizer.load(DEFAULT_CHECKPOINT)
            .encode(
                torch.from_numpy(
                    load_audio(tmp_path / "data" / "wave16k" / "1_agent_0_0_0_agent.wav", SAMPLE_RATE_HZ)[
                        : 50 * STEP_SAMPLES
                    ]
                )[None]
            )[0]
            .numpy()
        )
        np.testing.assert_array_equal(rec["audio_codes"], codes)  # the agent channel, as the runtime codes it
    LMDataset(tmp_path / "lm", 20, LOCAL_SPEC)  # readable by the LM trainer, spec checked


def test_tokenize_a_take_matches_the_codecs_own_encoding(tmp_path):
    _dyadic_take(tmp_path / "data")
    take = find_takes(tmp_path / "data")[0]
    codecs = load_codecs(CHECKPOINTS / "codecs")
    tok = tokenize_take(take, codecs, SpeechTokenizer.load(DEFAULT_CHECKPOINT))
    assert tok.gesture_tokens.min() >= 0 and tok.gesture_tokens.max() < codecs["upper"].codebook_size
    assert len(np.unique(tok.gesture_tokens[0])) > 1


# ---------------------------------------------------------------- the training chain (slow)


@pytest.mark.slow
def test_training_chain_end_to_end_tiny(tmp_path):
    env = {
        **os.environ,
        "SESSIONS": "2",
        "MINUTES": "0.5",
        "CODEC_STEPS": "10",
        "DECODER_REGIONS": "upper lower",
        "DECODER_STEPS": "4",
        "LM_EPOCHS": "1",
        "WORK": str(tmp_path / "work"),
        "SHIP": str(tmp_path / "ship"),
        "SYNTHETIC": str(tmp_path / "synthetic"),
        "PY": str(REPO / ".venv" / "bin" / "python"),
    }
    subprocess.run(
        ["bash", str(REPO / "scripts" / "train_default.sh")],
        cwd=REPO,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    )
    times = dict(line.split("\t") for line in (tmp_path / "work" / "wall_times.tsv").read_text().splitlines())
    assert {"synthetic", "chunk_cache", "codecs", "decoders", "tokenize", "lm", "ship"} <= set(times)
    ship = tmp_path / "ship"
    lm = load_lm(ship / "gesture_lm", LOCAL_SPEC)
    assert next(iter(lm.state_dict().values())).dtype == torch.float32  # stored bf16, loaded as fp32
    codecs = load_codecs(ship / "codecs")
    assert set(codecs) == {"upper", "lower", "face"}
    tuned = (tmp_path / "work" / "decoders" / "upper" / "model.safetensors").read_bytes()
    assert (ship / "codecs" / "upper" / "model.safetensors").read_bytes() == tuned  # the fine-tuned decoder ships
    assert json.loads((ship / "gesture_lm" / "speakers.json").read_text())
    for card in ("codecs/README.md", "gesture_lm/README.md"):  # the cards name the generator that made the data
        assert generator_fingerprint()[:16] in (ship / card).read_text()
    # a second run trains only the lower codec and copies the others: its card says where each was trained
    again = {
        **env,
        "CODEC_REGIONS": "lower",
        "CODECS_FROM": str(tmp_path / "work"),
        "DECODER_REGIONS": "upper",
        "WORK": str(tmp_path / "work2"),
        "SHIP": str(tmp_path / "ship2"),
    }
    subprocess.run(
        ["bash", str(REPO / "scripts" / "train_default.sh")],
        cwd=REPO,
        env=again,
        check=True,
        capture_output=True,
        text=True,
    )
    card = (tmp_path / "ship2" / "codecs" / "README.md").read_text()
    assert f"- upper and face: copied unchanged from `{tmp_path / 'work'}`" in card
    assert "- lower: trained in this run" in card


def _train_default_fails(tmp_path, **options) -> str:
    """Run scripts/train_default.sh with these options, expecting it to stop before any stage: its error text."""
    env = {**os.environ, "WORK": str(tmp_path / "work"), "SYNTHETIC": str(tmp_path / "synthetic"), **options}
    run = subprocess.run(
        ["bash", str(REPO / "scripts" / "train_default.sh")], cwd=REPO, env=env, capture_output=True, text=True
    )
    assert run.returncode != 0
    assert not (tmp_path / "work").exists() and not (tmp_path / "synthetic").exists()
    return run.stderr


def test_training_chain_refuses_a_region_it_cannot_copy_before_any_stage(tmp_path):
    assert "leaves out upper: set CODECS_FROM" in _train_default_fails(tmp_path, CODEC_REGIONS="lower face")
    earlier = tmp_path / "earlier"
    for region in ("upper", "face"):
        (earlier / "codecs" / region).mkdir(parents=True)
        (earlier / "codecs" / region / "model.safetensors").write_bytes(b"")
    (earlier / "decoders" / "upper").mkdir(parents=True)  # that run shipped a fine-tuned upper decoder
    error = _train_default_fails(tmp_path, CODEC_REGIONS="lower", CODECS_FROM=str(earlier))
    assert "fine-tuned its upper decoder, which is not copied: add upper to DECODER_REGIONS" in error
