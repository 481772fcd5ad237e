"""Report files written atomically: to a temporary name in the same directory, flushed, then renamed.

A write that fails (a full disk, a file size limit, Ctrl-C) leaves the previous file, or none, and never a
truncated one; the temporary file is removed. Readers (the dashboard, `render.play`) never see half a file.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import IO


def temporary_name(path: Path) -> Path:
    """A hidden name beside `path`, unique to this process (two writers never share it)."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


@contextlib.contextmanager
def atomic_file(path: str | Path, mode: str = "wb") -> Iterator[IO]:
    """`with atomic_file(p) as f: f.write(...)`: `p` appears complete when the block ends without an error."""
    path = Path(path)
    tmp = temporary_name(path)
    try:
        with open(tmp, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | Path, text: str) -> None:
    with atomic_file(path, "w") as f:
        f.write(text)


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    with atomic_file(path, "wb") as f:
        f.write(data)
