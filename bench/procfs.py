"""The processes of this machine as Linux's /proc lists them: what the benches and the tests read about a run's
process tree (CPU time, session, parent) without psutil."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

# Fields of /proc/PID/stat after the command name, counted from 0
STATE, PARENT_PID, SESSION_ID, USER_TICKS, SYSTEM_TICKS = 0, 1, 3, 11, 12


def process_stats() -> Iterator[tuple[int, list[str]]]:
    """(pid, its /proc/PID/stat fields after the command name) for every process now; one that exits while being
    read is left out."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()  # the name, in parentheses, may hold spaces
        except (OSError, IndexError):
            continue
        yield int(stat.parent.name), fields


def session_pids(sid: int) -> list[int]:
    """Live (not zombie) processes whose session id is `sid`."""
    return [pid for pid, f in process_stats() if int(f[SESSION_ID]) == sid and f[STATE] != "Z"]
