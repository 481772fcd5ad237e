"""BEAT2 reader: take discovery, SMPL-X/FLAME motion npz, transcripts (whisper json, TextGrid) and splits.

Two layouts are accepted:
- the BEAT2 release layout (one language directory): ``smplxflame_30/`` or ``smplxflame_25/`` (``<id>.npz``),
  ``wave16k/<id>.wav``, ``whisper_transcription/<id>.json``, ``textgrid/<id>.TextGrid``, ``train_test_split.csv``;
- a bare directory with ``<id>.npz`` and optionally ``<id>.wav``, ``<id>.json`` and ``<id>.TextGrid`` side by side.

Take ids look like ``2_scott_0_1_1``; the speaker is the second ``_`` field.
"""

from __future__ import annotations

import csv
import json
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ecas.core.body import NUM_EXPRESSIONS, NUM_JOINTS
from ecas.core.errors import DataError
from gesture.data.textgrid import read_textgrid

MOTION_DIRS = ("smplxflame_25", "smplxflame_30")  # preferred first
AUDIO_DIRS = ("wave16k",)
TRANSCRIPT_DIR = "whisper_transcription"
TEXTGRID_DIR = "textgrid"
SPLIT_CSV = "train_test_split.csv"
SPLITS = {"train": "train", "additional": "train", "val": "val", "test": "test"}


@dataclass(frozen=True)
class Word:
    word: str
    start_s: float
    end_s: float


@dataclass(frozen=True)
class Take:
    """One recording and the files that belong to it (absent ones are None)."""

    take_id: str
    speaker: str
    split: str
    motion_path: Path
    audio_path: Optional[Path]
    transcript_path: Optional[Path]
    textgrid_path: Optional[Path]

    @property
    def source_paths(self) -> tuple[Path, ...]:
        paths = (self.motion_path, self.audio_path, self.transcript_path, self.textgrid_path)
        return tuple(p for p in paths if p is not None)


@dataclass(frozen=True)
class Motion:
    poses: np.ndarray  # (T, 55, 3) axis-angle, float32
    trans: np.ndarray  # (T, 3) metres, float32
    expressions: np.ndarray  # (T, 100) float32
    betas: np.ndarray  # (B,) float32
    fps: float


def speaker_of(take_id: str) -> str:
    fields = take_id.split("_")
    if len(fields) < 2 or not fields[1]:
        raise DataError(take_id, "take id has no speaker field (expected e.g. '2_scott_0_1_1')")
    return fields[1]


def read_split_csv(path: Path) -> dict[str, str]:
    """take id -> train | val | test ('additional' counts as train)."""
    try:
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as err:
        raise DataError(path, f"cannot read split file ({err})") from err
    if not rows or not {"id", "type"} <= set(rows[0]):
        raise DataError(path, "split file needs the columns 'id' and 'type'")
    splits = {}
    for line, row in enumerate(rows, start=2):
        kind = (row["type"] or "").strip()
        if kind not in SPLITS:
            raise DataError(path, f"line {line}: unknown split type {kind!r} (expected one of {sorted(SPLITS)})")
        splits[row["id"].strip()] = SPLITS[kind]
    return splits


def _first_existing(*candidates: Path) -> Optional[Path]:
    return next((p for p in candidates if p.is_file()), None)


def find_takes(root: Path | str, default_split: str = "train") -> list[Take]:
    """All takes under ``root`` (either layout), sorted by id."""
    root = Path(root)
    if not root.is_dir():
        raise DataError(root, "data root is not a directory")
    motion_dir = next((root / d for d in MOTION_DIRS if (root / d).is_dir()), root)
    split_path = root / SPLIT_CSV
    splits = read_split_csv(split_path) if split_path.is_file() else {}
    takes = []
    for npz in sorted(motion_dir.glob("*.npz")):
        take_id = npz.stem
        if take_id.startswith("mean_") or take_id.startswith("std_"):
            continue
        takes.append(
            Take(
                take_id=take_id,
                speaker=speaker_of(take_id),
                split=splits.get(take_id, default_split),
                motion_path=npz,
                audio_path=_first_existing(*(root / d / f"{take_id}.wav" for d in AUDIO_DIRS), root / f"{take_id}.wav"),
                transcript_path=_first_existing(root / TRANSCRIPT_DIR / f"{take_id}.json", root / f"{take_id}.json"),
                textgrid_path=_first_existing(
                    root / TEXTGRID_DIR / f"{take_id}.TextGrid", root / f"{take_id}.TextGrid"
                ),
            )
        )
    if not takes:
        raise DataError(root, f"no motion files (*.npz) found in {motion_dir}")
    return takes


def _array(data, key: str, path: Path) -> np.ndarray:
    if key not in data.files:
        raise DataError(path, f"motion file has no '{key}' array (has: {', '.join(sorted(data.files))})")
    return np.asarray(data[key])


def _fps_of(data, path: Path) -> float:
    if "mocap_frame_rate" in data.files:
        return float(np.asarray(data["mocap_frame_rate"]).reshape(-1)[0])
    for name in MOTION_DIRS:
        if name in path.parts:
            return float(name.rsplit("_", 1)[1])
    raise DataError(path, "motion file has no 'mocap_frame_rate' and its folder does not name the rate")


GESTURE_POSES_KEY = "gesture_poses"  # synthetic data: the poses without the agent's runtime micro-motion


def read_motion(path: Path | str, gesture_layer: bool = False) -> Motion:
    """A BEAT2 SMPL-X/FLAME npz: poses (T, 165), trans (T, 3), expressions (T, 100), betas, frame rate.
    ``gesture_layer``: the poses the codecs model, ``gesture_poses`` where the file has them (synthetic data, see
    gesture.synth.build), else ``poses``."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "motion file not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            key = GESTURE_POSES_KEY if gesture_layer and GESTURE_POSES_KEY in data.files else "poses"
            poses = _array(data, key, path)
            trans = _array(data, "trans", path)
            expressions = _array(data, "expressions", path)
            betas = _array(data, "betas", path) if "betas" in data.files else np.zeros(300)
            fps = _fps_of(data, path)
    except DataError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as err:  # truncated: BadZipFile
        raise DataError(path, f"not a readable npz ({' '.join(str(err).split())})") from None
    t = len(poses)
    if poses.ndim != 2 or poses.shape[1] != NUM_JOINTS * 3:
        raise DataError(path, f"'{key}' must be (T, {NUM_JOINTS * 3}), got {poses.shape}")
    if trans.shape != (t, 3):
        raise DataError(path, f"'trans' must be ({t}, 3) to match '{key}', got {trans.shape}")
    if expressions.shape != (t, NUM_EXPRESSIONS):
        raise DataError(
            path, f"'expressions' must be ({t}, {NUM_EXPRESSIONS}) to match '{key}', got {expressions.shape}"
        )
    if t < 2:
        raise DataError(path, f"motion has {t} frame(s); need at least 2")
    if fps <= 0:
        raise DataError(path, f"frame rate must be positive, got {fps}")
    for name, arr in ((key, poses), ("trans", trans), ("expressions", expressions)):
        if not np.isfinite(arr).all():
            raise DataError(path, f"'{name}' contains NaN or inf")
    return Motion(
        poses=poses.reshape(t, NUM_JOINTS, 3).astype(np.float32),
        trans=trans.astype(np.float32),
        expressions=expressions.astype(np.float32),
        betas=betas.reshape(-1).astype(np.float32),
        fps=fps,
    )


def read_whisper_words(path: Path | str) -> list[Word]:
    """Words of a whisper transcription json: segments[].words[] with word, start, end (seconds)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DataError(path, "transcript file not found") from None
    except (OSError, ValueError) as err:
        raise DataError(path, f"not valid JSON ({err})") from err
    if not isinstance(doc, dict) or not isinstance(doc.get("segments"), list):
        raise DataError(path, "transcript has no 'segments' list")
    words = []
    for i, seg in enumerate(doc["segments"]):
        for j, w in enumerate(seg.get("words", []) if isinstance(seg, dict) else []):
            try:
                words.append(Word(str(w["word"]).strip(), float(w["start"]), float(w["end"])))
            except (KeyError, TypeError, ValueError) as err:
                raise DataError(path, f"segments[{i}].words[{j}] needs word/start/end ({err!r})") from None
    return words


def read_textgrid_words(path: Path | str, tier: str = "words") -> list[Word]:
    """Non-empty intervals of a TextGrid's word tier (the first tier if none is named ``tier``)."""
    tiers = read_textgrid(path)
    if not tiers:
        raise DataError(path, "TextGrid has no tiers")
    chosen = next((t for t in tiers if t.name.lower() == tier), tiers[0])
    return [Word(i.text.strip(), i.start_s, i.end_s) for i in chosen.intervals if i.text.strip()]


def read_words(take: Take) -> list[Word]:
    """The take's words: whisper json if present, else its TextGrid, else none."""
    if take.transcript_path is not None:
        return read_whisper_words(take.transcript_path)
    if take.textgrid_path is not None:
        return read_textgrid_words(take.textgrid_path)
    return []
