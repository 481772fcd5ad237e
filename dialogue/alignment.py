"""Word timings of a whole recording: from a transcript file, by forced alignment, or by recognition.

Transcript formats: whisper json (`segments[].words[]` with `word/start/end`, or segment-level
`text/start/end` whose words share the segment evenly), Praat TextGrid (the first interval tier named like
"word", else the first interval tier), or plain text (aligned with pocketsphinx; words missing from its
dictionary cannot be aligned and are skipped).
"""

import json
import re
from pathlib import Path

import numpy as np

from dialogue.asr import FRAME_RATE_HZ, RecognizedWord, clean_word
from dialogue.resample import StreamResampler
from dialogue.vad import VAD_RATE_HZ

ALIGN_BEAMS = dict(beam=1e-80, pbeam=1e-80, wbeam=1e-60)  # forced alignment needs wide beams
TRAILING_SILENCE_S = 0.5


class TranscriptFormatError(ValueError):
    pass


def words_from_transcript(path: Path, pcm: np.ndarray, rate_hz: int) -> list[RecognizedWord]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"transcript not found: {path}")
    text = path.read_text(encoding="utf-8", errors="replace")
    if path.suffix.lower() == ".json":
        return _whisper_words(json.loads(text), path)
    if path.suffix.lower() == ".textgrid" or text.lstrip().startswith('File type = "ooTextFile"'):
        return _textgrid_words(text, path)
    return align_text(text, pcm, rate_hz)


def _whisper_words(doc: dict, path: Path) -> list[RecognizedWord]:
    segments = doc.get("segments") if isinstance(doc, dict) else None
    if not isinstance(segments, list):
        raise TranscriptFormatError(f"{path}: not a whisper json (no 'segments' list)")
    words = []
    for seg in segments:
        if seg.get("words"):
            words += [
                RecognizedWord(w["word"].strip(), float(w["start"]), float(w["end"]))
                for w in seg["words"]
                if w.get("word", "").strip()
            ]
        else:
            tokens = seg.get("text", "").split()
            edges = np.linspace(float(seg["start"]), float(seg["end"]), len(tokens) + 1)
            words += [RecognizedWord(t, float(a), float(b)) for t, a, b in zip(tokens, edges[:-1], edges[1:])]
    return words


def _textgrid_words(text: str, path: Path) -> list[RecognizedWord]:
    tiers = re.split(r"item\s*\[\d+\]\s*:", text)[1:]
    if not tiers:
        raise TranscriptFormatError(f"{path}: no tiers found in the TextGrid")
    interval_tiers = [t for t in tiers if "IntervalTier" in t]
    chosen = next((t for t in interval_tiers if re.search(r'name\s*=\s*"[^"]*word', t, re.IGNORECASE)), None)
    chosen = chosen or (interval_tiers[0] if interval_tiers else None)
    if chosen is None:
        raise TranscriptFormatError(f"{path}: no interval tier in the TextGrid")
    pattern = re.compile(r'xmin\s*=\s*([\d.]+)\s*xmax\s*=\s*([\d.]+)\s*text\s*=\s*"([^"]*)"')
    return [RecognizedWord(w.strip(), float(a), float(b)) for a, b, w in pattern.findall(chosen) if w.strip()]


def _to_16k_int16(pcm: np.ndarray, rate_hz: int) -> bytes:
    x = StreamResampler(rate_hz, VAD_RATE_HZ).process(pcm)
    x = np.concatenate([x, np.zeros(int(TRAILING_SILENCE_S * VAD_RATE_HZ), np.float32)])
    return (np.clip(x, -1, 1) * 32767).astype(np.int16).tobytes()


def _segments(decoder) -> list[RecognizedWord]:
    out = []
    for seg in decoder.seg():
        word = clean_word(seg.word)
        if word:
            out.append(RecognizedWord(word, seg.start_frame / FRAME_RATE_HZ, (seg.end_frame + 1) / FRAME_RATE_HZ))
    return out


def align_text(text: str, pcm: np.ndarray, rate_hz: int) -> list[RecognizedWord]:
    """Forced alignment of plain text to the recording (pocketsphinx, wide beams, trailing silence)."""
    from pocketsphinx import Decoder

    decoder = Decoder(samprate=VAD_RATE_HZ, loglevel="FATAL", **ALIGN_BEAMS)
    words = [w for w in re.findall(r"[a-z']+", text.lower()) if decoder.lookup_word(w) is not None]
    if not words:
        raise TranscriptFormatError("the transcript has no word that the aligner's dictionary knows")
    decoder.set_align_text(" ".join(words))
    decoder.start_utt()
    decoder.process_raw(_to_16k_int16(pcm, rate_hz), False, True)
    decoder.end_utt()
    return _segments(decoder)


def recognize(pcm: np.ndarray, rate_hz: int) -> list[RecognizedWord]:
    """Words of a whole recording by recognition (no transcript)."""
    from pocketsphinx import Decoder

    decoder = Decoder(samprate=VAD_RATE_HZ, loglevel="FATAL")
    decoder.start_utt()
    decoder.process_raw(_to_16k_int16(pcm, rate_hz), False, True)
    decoder.end_utt()
    return _segments(decoder)
