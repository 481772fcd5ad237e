"""Turn a BEAT2-layout directory into the gesture LM's training set (the npz format of `gesture.lm.data`).

    ecas tokenize --root DIR --codecs CODECS_DIR --out LM_DATA_DIR [--splits train]

Per take, at 12.5 steps/s (T steps = frames // 2):
- `gesture_tokens` (20, T): the take's motion (25 fps, canonicalised once at its first frame) through the three
  trained codecs' encoders, in LM level order (upper 0-7, lower 8-15, face 16-19);
- `audio_codes` (8, T): the AGENT's speech at 24 kHz through the local backend's speech tokenizer, exactly the
  codes the runtime sees (silence has codes too);
- `text_tokens` (T,): the local text vocabulary's id of each agent word at the step where it starts; a word
  whose step is taken goes to the next free step, as the runtime speaker queues them; −1 elsewhere;
- `vad` (T,): the agent's voice activity per step, "either frame active" of the per-frame labels (`vad` in the
  motion npz, as the synthetic generator writes it), else from the agent's word intervals (BEAT2);
  a take without a transcript gets its words from the local recogniser (pocketsphinx), as the playback backend
  does at run time;
- `speaker` (): the speaker's index in `speakers.json` (sorted names) or a fixed index (`--speaker`).

The agent's audio is `<id>_agent.wav` beside the take's wav when present (a dyadic session), else the take's own
wav (BEAT2: the take's speaker is the one who moves). Agent words are the transcript words whose `speaker` field
names the agent ("agent" or the take's speaker), or all words when there is no such field.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dialogue.speech_tokenizer import DEFAULT_CHECKPOINT, SpeechTokenizer
from dialogue.text_vocab import LOCAL_SPEC, word_token
from ecas.core.body import REGIONS
from ecas.core.errors import DataError
from ecas.core.spec import ConditionSpec
from ecas.core.threads import limit_threads
from ecas.core.timing import FRAMES_PER_STEP, MOTION_FPS, SAMPLE_RATE_HZ, STEP_HZ, STEP_SAMPLES
from gesture.body.motion import canonicalize
from gesture.body.regions import motion_to_features
from gesture.codec.model import GestureCodec
from gesture.data.audio import load_audio
from gesture.data.beat2 import Take, Word, find_takes, read_motion, read_words
from gesture.data.chunks import motion_at_fps
from gesture.lm.codecs import load_codecs
from gesture.lm.data import write_recording, write_spec

AGENT_WAV_SUFFIX = "_agent"
AGENT_SPEAKER_NAMES = ("agent",)
SPEAKERS_FILE = "speakers.json"
VAD_KEY = "vad"


@dataclass(frozen=True)
class TokenizedTake:
    gesture_tokens: np.ndarray  # (K, T) int
    text_tokens: np.ndarray  # (T,) int, −1 = none
    audio_codes: np.ndarray  # (Q, T) int
    vad: np.ndarray  # (T,) {0, 1}

    @property
    def num_steps(self) -> int:
        return self.gesture_tokens.shape[1]


# ---------------------------------------------------------------- one signal at a time


@torch.no_grad()
def encode_motion(
    codecs: dict[str, GestureCodec], poses: np.ndarray, trans: np.ndarray, expressions: np.ndarray
) -> np.ndarray:
    """25 fps motion (T frames) -> (20, T // 2) gesture tokens, canonicalised at its first frame."""
    frames = len(poses) // FRAMES_PER_STEP * FRAMES_PER_STEP
    poses, trans = canonicalize(poses[:frames], trans[:frames])
    features = motion_to_features(poses, trans, expressions[:frames], MOTION_FPS)  # region -> (T, F)
    codes = [codecs[r].eval().encode(torch.from_numpy(features[r])[None])[0] for r in REGIONS]  # (K_r, S) each
    return torch.cat(codes).numpy().astype(np.int64)  # (K, S)


@torch.no_grad()
def encode_speech(tokenizer: SpeechTokenizer, pcm_24k: np.ndarray, n_steps: int) -> np.ndarray:
    """(N,) 24 kHz audio -> (8, n_steps) speech codes; audio is zero-padded or cut to n_steps steps."""
    pcm = np.zeros(n_steps * STEP_SAMPLES, np.float32)
    piece = pcm_24k[: len(pcm)]
    pcm[: len(piece)] = piece
    return tokenizer.encode(torch.from_numpy(pcm)[None])[0].numpy().astype(np.int64)  # (Q, S)


def place_words(words: Sequence[Word], n_steps: int) -> np.ndarray:
    """(n_steps,) text tokens: each word's id at the step where it starts, or the next free step."""
    tokens = np.full(n_steps, -1, np.int64)
    next_free = 0
    for word in sorted(words, key=lambda w: w.start_s):
        token = word_token(word.word)
        step = max(int(np.floor(word.start_s * STEP_HZ + 1e-9)), next_free)
        if token < 0 or step >= n_steps:
            continue
        tokens[step] = token
        next_free = step + 1
    return tokens


def vad_from_frames(frame_vad: np.ndarray, n_steps: int) -> np.ndarray:
    """Per-frame (25 fps) voice activity -> (n_steps,) {0, 1}: a step is active when either frame is."""
    frames = np.zeros(n_steps * FRAMES_PER_STEP, np.float32)
    piece = np.asarray(frame_vad, np.float32).reshape(-1)[: len(frames)]
    frames[: len(piece)] = piece
    return (frames.reshape(n_steps, FRAMES_PER_STEP) > 0.5).any(axis=1).astype(np.uint8)  # (S,)


def vad_from_words(words: Sequence[Word], n_steps: int) -> np.ndarray:
    """(n_steps,) {0, 1}: steps that overlap a word interval."""
    vad = np.zeros(n_steps, np.uint8)
    for w in words:
        first = max(0, int(np.floor(w.start_s * STEP_HZ)))
        last = min(n_steps, int(np.ceil(w.end_s * STEP_HZ)))
        vad[first:last] = 1
    return vad


# ---------------------------------------------------------------- a take


def agent_audio_path(take: Take) -> Path | None:
    if take.audio_path is None:
        return None
    dyadic = take.audio_path.with_name(f"{take.take_id}{AGENT_WAV_SUFFIX}.wav")
    return dyadic if dyadic.is_file() else take.audio_path


def recognized_words(pcm_24k: np.ndarray) -> list[Word]:
    from dialogue.alignment import recognize

    return [Word(w.word, w.start_s, w.end_s) for w in recognize(pcm_24k, SAMPLE_RATE_HZ)]


def agent_words(take: Take, pcm_24k: np.ndarray) -> list[Word]:
    """The words the agent speaks (see the module docstring)."""
    if take.transcript_path is None and take.textgrid_path is None:
        return recognized_words(pcm_24k)
    if take.transcript_path is None:
        return read_words(take)
    doc = json.loads(take.transcript_path.read_text(encoding="utf-8"))
    entries = [w for seg in doc.get("segments", []) for w in seg.get("words", [])]
    if not any("speaker" in w for w in entries):
        return read_words(take)
    names = {*AGENT_SPEAKER_NAMES, take.speaker}
    return [
        Word(str(w["word"]).strip(), float(w["start"]), float(w["end"]))
        for w in entries
        if str(w.get("speaker", "")) in names
    ]


def frame_vad_of(take: Take) -> np.ndarray | None:
    """The per-frame agent voice activity stored in the motion npz (25 fps), if any."""
    with np.load(take.motion_path, allow_pickle=False) as data:
        return np.asarray(data[VAD_KEY]) if VAD_KEY in data.files else None


def tokenize_take(take: Take, codecs: dict[str, GestureCodec], tokenizer: SpeechTokenizer) -> TokenizedTake:
    motion = motion_at_fps(read_motion(take.motion_path, gesture_layer=True), MOTION_FPS)
    gesture_tokens = encode_motion(codecs, motion.poses, motion.trans, motion.expressions)  # (K, S)
    n_steps = gesture_tokens.shape[1]
    audio_path = agent_audio_path(take)
    if audio_path is None:
        raise DataError(take.motion_path, "take has no wav: the LM needs the agent's speech")
    pcm = load_audio(audio_path, SAMPLE_RATE_HZ)
    audio_codes = encode_speech(tokenizer, pcm, n_steps)
    words = agent_words(take, pcm)
    frame_vad = frame_vad_of(take)
    if frame_vad is not None and motion.fps != MOTION_FPS:
        raise DataError(take.motion_path, f"'{VAD_KEY}' labels need motion at {MOTION_FPS} fps, got {motion.fps}")
    vad = vad_from_frames(frame_vad, n_steps) if frame_vad is not None else vad_from_words(words, n_steps)
    return TokenizedTake(gesture_tokens, place_words(words, n_steps), audio_codes, vad)


# ---------------------------------------------------------------- a directory


def speaker_indices(takes: Sequence[Take], fixed: int | None) -> dict[str, int]:
    names = sorted({t.speaker for t in takes})
    return {name: fixed for name in names} if fixed is not None else {name: i for i, name in enumerate(names)}


def tokenize_directory(
    root: Path,
    codecs_dir: Path,
    out_dir: Path,
    splits: Sequence[str] = ("train",),
    speaker: int | None = None,
    tokenizer_path: Path = DEFAULT_CHECKPOINT,
    spec: ConditionSpec = LOCAL_SPEC,
    progress=iter,
) -> dict:
    """Write one npz per take of `splits` plus spec.json and speakers.json; returns a summary."""
    takes = [t for t in find_takes(root) if t.split in splits]
    if not takes:
        raise DataError(root, f"no takes in split(s) {', '.join(splits)}")
    codecs = load_codecs(codecs_dir)
    tokenizer = SpeechTokenizer.load(tokenizer_path)
    speakers = speaker_indices(takes, speaker)
    out_dir.mkdir(parents=True, exist_ok=True)
    steps, active = 0, 0
    for take in progress(takes):
        tok = tokenize_take(take, codecs, tokenizer)
        write_recording(
            out_dir / f"{take.take_id}.npz",
            tok.gesture_tokens,
            tok.text_tokens,
            tok.audio_codes,
            tok.vad,
            speakers[take.speaker],
        )
        steps += tok.num_steps
        active += int(tok.vad.sum())
    write_spec(out_dir, spec)
    (out_dir / SPEAKERS_FILE).write_text(json.dumps(speakers, indent=1))
    return {
        "takes": len(takes),
        "steps": steps,
        "hours": steps / STEP_HZ / 3600,
        "vad_active_fraction": active / max(steps, 1),
        "speakers": speakers,
    }


def main(argv=None) -> int:
    limit_threads()
    from tqdm import tqdm

    parser = argparse.ArgumentParser(
        prog="ecas tokenize", description="Tokenize a BEAT2-layout directory for gesture LM training."
    )
    parser.add_argument("--root", type=Path, required=True, help="BEAT2-layout directory (or bare <id>.npz/.wav)")
    parser.add_argument("--codecs", type=Path, required=True, help="directory with the upper/, lower/, face/ codecs")
    parser.add_argument("--out", type=Path, required=True, help="output directory of npz recordings")
    parser.add_argument("--splits", nargs="+", default=["train"], help="splits to tokenize (default: train)")
    parser.add_argument("--speaker", type=int, help="one speaker index for every take (default: sorted names)")
    parser.add_argument("--speech-tokenizer", type=Path, default=DEFAULT_CHECKPOINT)
    args = parser.parse_args(argv)
    for flag, path in (("--root", args.root), ("--codecs", args.codecs)):
        if not path.is_dir():
            print(f"error: {flag} {path}: not a directory", file=sys.stderr)
            return 2
    try:
        summary = tokenize_directory(
            args.root,
            args.codecs,
            args.out,
            args.splits,
            args.speaker,
            args.speech_tokenizer,
            progress=lambda xs: tqdm(xs, desc="takes", unit="take"),
        )
    except (DataError, FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
