"""The cached BEAT2 chunks as a torch Dataset (for codec and gesture-LM training)."""

from __future__ import annotations

from collections import OrderedDict
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from gesture.data.cache import load_shard, read_manifest

TENSOR_KEYS = ("upper", "lower", "face", "poses", "trans", "expressions", "audio")


class Beat2Chunks(Dataset):
    """Per-chunk dicts: region features, canonical motion, audio, words, speaker.

    Items: ``upper`` (F, 258), ``lower`` (F, 61), ``face`` (F, 106), ``poses`` (F, 55, 3), ``trans`` (F, 3),
    ``expressions`` (F, 100), ``audio`` (S,) float32 tensors; ``words`` list of (word, start_s, end_s) relative
    to the chunk; ``speaker``, ``take_id``, ``split`` strings; ``chunk_index`` int; ``start_s`` float.
    """

    def __init__(
        self,
        cache_dir: Path | str,
        splits: Optional[Sequence[str]] = None,
        speakers: Optional[Sequence[str]] = None,
        max_open_shards: int = 8,
    ):
        self.cache_dir = Path(cache_dir)
        manifest = read_manifest(self.cache_dir)
        self.options = manifest["options"]
        self.index: list[tuple[str, str, int]] = []  # (take id, shard file, chunk)
        self.takes = {}
        for take_id, entry in sorted(manifest["takes"].items()):
            if (splits and entry["split"] not in splits) or (speakers and entry["speaker"] not in speakers):
                continue
            self.takes[take_id] = entry
            self.index += [(take_id, entry["shard"], i) for i in range(entry["num_chunks"])]
        self.speakers = sorted({e["speaker"] for e in self.takes.values()})
        self._shards: OrderedDict[str, dict] = OrderedDict()
        self._max_open = max_open_shards

    def __len__(self) -> int:
        return len(self.index)

    def _shard(self, name: str) -> dict:
        if name not in self._shards:
            self._shards[name] = load_shard(self.cache_dir / name)
            if len(self._shards) > self._max_open:
                self._shards.popitem(last=False)
        self._shards.move_to_end(name)
        return self._shards[name]

    def __getitem__(self, i: int) -> dict:
        take_id, shard_name, chunk = self.index[i]
        shard = self._shard(shard_name)
        entry = self.takes[take_id]
        item = {k: torch.from_numpy(np.ascontiguousarray(shard[k][chunk])) for k in TENSOR_KEYS}
        item.update(
            words=list(shard["words"][chunk]),
            speaker=entry["speaker"],
            take_id=take_id,
            split=entry["split"],
            chunk_index=chunk,
            start_s=float(shard["start_s"][chunk]),
        )
        return item


def collate_chunks(items: list[dict]) -> dict:
    """Stack tensors (B, ...); keep words and strings as lists."""
    out = {k: torch.stack([it[k] for it in items]) for k in TENSOR_KEYS}
    for key in ("words", "speaker", "take_id", "split", "chunk_index", "start_s"):
        out[key] = [it[key] for it in items]
    return out
