"""A small Praat TextGrid reader (long and short text formats, UTF-8 or UTF-16).

Both formats carry the same sequence of values; the long one only adds labels
(``xmin = ``, ``item [1]:``). The reader keeps the values and drops the labels.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from ecas.core.errors import DataError

_TOKEN = re.compile(r'"(?:[^"]|"")*"|\[\s*\d*\s*\]|<\w+>|[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?|\.\d+')


@dataclass(frozen=True)
class Interval:
    start_s: float
    end_s: float
    text: str


@dataclass(frozen=True)
class Tier:
    name: str
    kind: str  # "IntervalTier" or "TextTier"
    intervals: tuple[Interval, ...]  # TextTier points have start_s == end_s


def _decode(raw: bytes) -> str:
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        return raw.decode("utf-16")
    return raw.decode("utf-8-sig")


def _tokens(text: str) -> list:
    out = []
    for tok in _TOKEN.findall(text):
        if tok.startswith("["):
            continue
        if tok.startswith('"'):
            out.append(tok[1:-1].replace('""', '"'))
        elif tok.startswith("<"):
            out.append(tok)
        else:
            out.append(float(tok))
    return out


class _Reader:
    def __init__(self, tokens: list, path: Path):
        self.tokens, self.pos, self.path = tokens, 0, path

    def take(self, kind: type, what: str):
        if self.pos >= len(self.tokens):
            raise DataError(self.path, f"TextGrid ends early: expected {what}")
        tok = self.tokens[self.pos]
        self.pos += 1
        if not isinstance(tok, kind):
            raise DataError(self.path, f"TextGrid: expected {what}, got {tok!r}")
        return tok


def parse_textgrid(text: str, path: Path | str = "<text>") -> list[Tier]:
    path = Path(path)
    r = _Reader(_tokens(text), path)
    if r.take(str, 'file type "ooTextFile"') != "ooTextFile" or r.take(str, "object class") != "TextGrid":
        raise DataError(path, 'not a Praat TextGrid (header must be "ooTextFile" / "TextGrid")')
    r.take(float, "xmin")
    r.take(float, "xmax")
    if r.take(str, "<exists> or <absent>") != "<exists>":
        return []
    tiers = []
    for _ in range(int(r.take(float, "number of tiers"))):
        kind = r.take(str, "tier class")
        name = r.take(str, "tier name")
        r.take(float, "tier xmin")
        r.take(float, "tier xmax")
        items = []
        for _ in range(int(r.take(float, "number of intervals"))):
            if kind == "IntervalTier":
                start, end = r.take(float, "interval xmin"), r.take(float, "interval xmax")
                items.append(Interval(start, end, r.take(str, "interval text")))
            elif kind == "TextTier":
                t = r.take(float, "point time")
                items.append(Interval(t, t, r.take(str, "point mark")))
            else:
                raise DataError(path, f"TextGrid: unknown tier class {kind!r}")
        tiers.append(Tier(name, kind, tuple(items)))
    return tiers


def read_textgrid(path: Path | str) -> list[Tier]:
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "TextGrid file not found")
    try:
        text = _decode(path.read_bytes())
    except UnicodeDecodeError as err:
        raise DataError(path, f"TextGrid is neither UTF-8 nor UTF-16 ({err})") from err
    return parse_textgrid(text, path)
