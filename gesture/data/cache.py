"""The chunk cache: one npz shard per take plus ``manifest.json`` with source fingerprints.

A take is rebuilt when the chunking options change or when one of its source files changed
(size or mtime differ AND the content hash differs; a touched but identical file is reused).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path
from typing import Callable, Iterable, Optional

import numpy as np

from ecas.core.errors import DataError
from gesture.body.skeleton import Skeleton
from gesture.data.beat2 import Take, Word
from gesture.data.chunks import TakeChunks, chunk_take
from gesture.data.config import DataConfig

CACHE_FORMAT = 1
MANIFEST = "manifest.json"
ARRAY_KEYS = ("upper", "lower", "face", "poses", "trans", "expressions", "audio", "start_s", "betas")


def file_fingerprint(path: Path) -> dict:
    stat = path.stat()
    return {"size": stat.st_size, "mtime_ns": stat.st_mtime_ns}


def file_sha1(path: Path) -> str:
    h = hashlib.sha1()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def chunking_options(cfg: DataConfig) -> dict:
    keys = ("motion_fps", "chunk_frames", "audio_sample_rate_hz", "smplx_model")
    return {"format": CACHE_FORMAT, **{k: getattr(cfg, k) for k in keys}}


def read_manifest(cache_dir: Path) -> dict:
    path = Path(cache_dir) / MANIFEST
    if not path.is_file():
        raise DataError(path, "no chunk cache here; build it with `python -m gesture.data.build --root DIR --out CACHE`")
    try:
        return json.loads(path.read_text())
    except ValueError as err:
        raise DataError(path, f"manifest is not valid JSON ({err})") from err


def _sources_unchanged(take: Take, recorded: dict) -> Optional[dict]:
    """The take's up-to-date source records if its files are unchanged, else None."""
    current = {}
    if set(recorded) != {str(p) for p in take.source_paths}:
        return None
    for path in take.source_paths:
        old = recorded[str(path)]
        fp = file_fingerprint(path)
        if fp == {"size": old["size"], "mtime_ns": old["mtime_ns"]}:
            current[str(path)] = old
            continue
        sha1 = file_sha1(path)
        if fp["size"] != old["size"] or sha1 != old["sha1"]:
            return None
        current[str(path)] = {**fp, "sha1": sha1}
    return current


def _source_records(take: Take) -> dict:
    return {str(p): {**file_fingerprint(p), "sha1": file_sha1(p)} for p in take.source_paths}


def _words_json(words: tuple[tuple[Word, ...], ...]) -> str:
    return json.dumps([[dataclasses.astuple(w) for w in chunk] for chunk in words])


def write_shard(path: Path, chunks: TakeChunks) -> None:
    tmp = path.with_suffix(".tmp.npz")
    arrays = {k: getattr(chunks, k) for k in ARRAY_KEYS}
    np.savez(tmp, **arrays, words_json=np.array(_words_json(chunks.words)))
    os.replace(tmp, path)


def build_cache(
    takes: Iterable[Take],
    cfg: DataConfig,
    out_dir: Path,
    progress: Callable[[Iterable[Take]], Iterable[Take]] = iter,
) -> dict:
    """Build or refresh the cache in ``out_dir``; returns the manifest (with build counts)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    options = chunking_options(cfg)
    try:
        old = read_manifest(out_dir)
    except DataError:
        old = {}
    old_takes = old.get("takes", {}) if old.get("options") == options else {}
    skeleton = Skeleton.from_smplx_model(cfg.smplx_model) if cfg.smplx_model else Skeleton.default()
    takes = list(takes)
    entries, built, reused = {}, 0, 0
    for take in progress(takes):
        shard = out_dir / f"{take.take_id}.npz"
        previous = old_takes.get(take.take_id)
        sources = _sources_unchanged(take, previous["sources"]) if previous and shard.is_file() else None
        if sources is not None:
            entries[take.take_id] = {**previous, "sources": sources, "split": take.split}
            reused += 1
            continue
        chunks = chunk_take(take, cfg, skeleton)
        write_shard(shard, chunks)
        entries[take.take_id] = {
            "shard": shard.name,
            "speaker": take.speaker,
            "split": take.split,
            "num_chunks": chunks.num_chunks,
            "has_audio": chunks.has_audio,
            "sources": _source_records(take),
        }
        built += 1
    for stale in set(old.get("takes", {})) - set(entries):
        (out_dir / f"{stale}.npz").unlink(missing_ok=True)
    manifest = {"options": options, "takes": entries}
    (out_dir / MANIFEST).write_text(json.dumps(manifest, indent=1, sort_keys=True))
    return {**manifest, "built": built, "reused": reused}


def load_shard(path: Path) -> dict:
    """A shard's arrays plus ``words``: per chunk a list of (word, start_s, end_s)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            out = {k: data[k] for k in ARRAY_KEYS}
            out["words"] = [[tuple(w) for w in chunk] for chunk in json.loads(str(data["words_json"]))]
    except (OSError, ValueError, KeyError) as err:
        raise DataError(path, f"broken cache shard ({err!r}); rebuild the cache") from err
    return out
