"""A report directory belongs to one run: the launcher holds an exclusive lock on `<report>/.lock` for the run.

The lock is `flock`: the kernel releases it when the launcher exits, however it exits (even SIGKILL), so a
crashed run never blocks the next one. A second run naming the same `--report` while the first runs gets one
line naming the first run's pid. The file is removed when the run ends; a run that locked a file another run
has just removed tries again on the new one.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from ecas.core.config import ConfigError

LOCK_FILE = ".lock"


class ReportLock:
    def __init__(self, directory: Path, option: str = "--report"):
        self.path = Path(directory) / LOCK_FILE
        self.option = option
        self.fd: int | None = None

    def acquire(self) -> ReportLock:
        """Take the lock or raise ConfigError (one line, naming the run that holds it)."""
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o644)
            except OSError as e:
                raise ConfigError(f"{self.option} {self.path.parent}: cannot lock it ({e.strerror or e})") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
                os.close(fd)
                raise ConfigError(
                    f"{self.option} {self.path.parent}: another run (pid {holder}) is writing its report there; "
                    "give another directory or wait for it to end"
                ) from None
            if _same_file(fd, self.path):
                break
            os.close(fd)  # the holder removed this file as we opened it: lock the new one
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is None:
            return
        self.path.unlink(missing_ok=True)
        os.close(self.fd)
        self.fd = None


def _same_file(fd: int, path: Path) -> bool:
    try:
        return os.stat(path, follow_symlinks=False).st_ino == os.fstat(fd).st_ino
    except FileNotFoundError:
        return False
