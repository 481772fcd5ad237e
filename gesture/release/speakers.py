"""Speakers of a converted release: `speakers.json` (name -> row of the speaker tables) beside the LM weights,
and `--character NAME|INDEX` resolution.

    python -m gesture.release.speakers checkpoints/miburi-release/lm                 list the speakers
    python -m gesture.release.speakers checkpoints/miburi-release/lm --character wayne
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Mapping
from pathlib import Path

from ecas.core.config import ConfigError
from gesture.lm.checkpoint import read_meta

SPEAKERS_FILE = "speakers.json"


def write_speaker_map(lm_dir: Path, speakers: Mapping[str, int]) -> None:
    (Path(lm_dir) / SPEAKERS_FILE).write_text(
        json.dumps(dict(sorted(speakers.items(), key=lambda kv: kv[1])), indent=1)
    )


def read_speaker_map(lm_dir: Path) -> dict[str, int]:
    """The speaker map of an LM checkpoint directory (empty when it has none, e.g. our own trained LMs)."""
    path = Path(lm_dir) / SPEAKERS_FILE
    return json.loads(path.read_text()) if path.is_file() else {}


def resolve_character(value: str | int, speakers: Mapping[str, int], n_speakers: int) -> int:
    """A speaker name (case-insensitive) or a row index in [0, n_speakers) -> the row index."""
    text = str(value).strip()
    if text.lstrip("-").isdigit():
        index = int(text)
        if not 0 <= index < n_speakers:
            raise ConfigError(
                f"--character: index {index} is outside the model's {n_speakers} speakers (0..{n_speakers - 1})"
            )
        return index
    by_name = {name.lower(): index for name, index in speakers.items()}
    if text.lower() not in by_name:
        known = ", ".join(f"{name} ({index})" for name, index in sorted(speakers.items(), key=lambda kv: kv[1]))
        raise ConfigError(f"--character: unknown speaker {text!r}; known: {known or 'none (give an index)'}")
    return by_name[text.lower()]


def resolve_character_for_checkpoint(lm_dir: Path, value: str | int) -> int:
    """`resolve_character` against the speaker map and speaker-table size of an LM checkpoint directory."""
    n_speakers = int(read_meta(lm_dir)["lm"]["n_speakers"])
    return resolve_character(value, read_speaker_map(lm_dir), n_speakers)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="ecas speakers", description="List the speakers of a converted LM, or resolve --character."
    )
    p.add_argument("lm_dir", type=Path, help="an LM checkpoint directory (e.g. checkpoints/miburi-release/lm)")
    p.add_argument("--character", help="speaker name or index")
    args = p.parse_args(argv)
    try:
        if args.character is not None:
            print(resolve_character_for_checkpoint(args.lm_dir, args.character))
            return 0
        for name, index in sorted(read_speaker_map(args.lm_dir).items(), key=lambda kv: kv[1]):
            print(f"{index:4d}  {name}")
    except (ConfigError, FileNotFoundError) as e:
        print(f"error: {e}")
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
