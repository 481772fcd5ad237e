"""Build the BEAT2 chunk cache once: ``python -m gesture.data.build --root DIR --out CACHE``.

Re-running reuses every take whose sources and chunking options are unchanged.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tqdm import tqdm

from ecas.core.config import ConfigError
from ecas.core.errors import DataError
from ecas.core.threads import limit_threads
from gesture.data.beat2 import find_takes
from gesture.data.cache import build_cache
from gesture.data.config import DataConfig, load_data_config


def main(argv=None) -> int:
    limit_threads()
    parser = argparse.ArgumentParser(prog="ecas data-build", description=__doc__.splitlines()[0])
    parser.add_argument("--root", help="BEAT2 language directory, or a directory of <id>.npz/.wav files")
    parser.add_argument("--out", help="cache directory")
    parser.add_argument("--config", help="YAML with data options (ecas/configs/data/*.yaml); --root/--out override it")
    args = parser.parse_args(argv)
    try:
        cfg = load_data_config(args.config) if args.config else DataConfig()
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    root, out = Path(args.root or cfg.root), Path(args.out or cfg.cache_dir)
    try:
        takes = [t for t in find_takes(root, cfg.default_split) if t.speaker not in cfg.exclude_speakers]
        result = build_cache(takes, cfg, out, progress=lambda xs: tqdm(xs, desc="takes", unit="take"))
    except DataError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    n_chunks = sum(t["num_chunks"] for t in result["takes"].values())
    print(
        f"{out}: {len(result['takes'])} takes ({result['built']} built, {result['reused']} reused), {n_chunks} chunks"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
