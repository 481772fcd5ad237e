"""espeak-ng text-to-speech through libespeak-ng (ctypes), with the sample index of every word.

The library synthesises synchronously at 22050 Hz; `EspeakTts.synthesize` resamples to 24 kHz and maps
each WORD event's exact sample index to the 24 kHz timeline. Voice variants with breath noise (e.g. the default
"en-us+f3") draw from libc's `rand()`, which other libraries in the process share, so every synthesis first seeds
it from the text: the same sentence always gives the same samples, and offline runs are reproducible.
"""

import ctypes
import ctypes.util
import re
import threading
import zlib
from dataclasses import dataclass

import numpy as np
from scipy.signal import resample_poly

from ecas.core.timing import SAMPLE_RATE_HZ

ESPEAK_RATE_HZ = 22_050
_RESAMPLE_UP, _RESAMPLE_DOWN = 160, 147  # 22050 * 160 / 147 = 24000

_AUDIO_OUTPUT_SYNCHRONOUS = 2
_INITIALIZE_PHONEME_EVENTS = 0x0001
_POS_CHARACTER = 1
_CHARS_UTF8 = 1
_EVENT_LIST_TERMINATED = 0
_EVENT_WORD = 1
_PARAM_RATE, _PARAM_VOLUME, _PARAM_PITCH = 1, 2, 3


class _EventId(ctypes.Union):
    _fields_ = [("number", ctypes.c_int), ("name", ctypes.c_char_p), ("string", ctypes.c_char * 8)]


class _Event(ctypes.Structure):
    _fields_ = [
        ("type", ctypes.c_int),
        ("unique_identifier", ctypes.c_uint),
        ("text_position", ctypes.c_int),
        ("length", ctypes.c_int),
        ("audio_position", ctypes.c_int),
        ("sample", ctypes.c_int),
        ("user_data", ctypes.c_void_p),
        ("id", _EventId),
    ]


_SynthCallback = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int, ctypes.POINTER(_Event))


class TtsError(RuntimeError):
    pass


@dataclass(frozen=True)
class WordTiming:
    word: str
    start_sample: int  # at 24 kHz, from the start of the utterance


@dataclass(frozen=True)
class Utterance:
    text: str
    pcm: np.ndarray  # (N,) float32 at 24 kHz
    words: tuple[WordTiming, ...]


_LIB_LOCK = threading.Lock()
_LIB = None
_LIBC = ctypes.CDLL(None)  # the process's own libc: espeak-ng's noise uses its rand()


def _load_library():
    """libespeak-ng is a process-wide singleton: load and initialise it once."""
    global _LIB
    with _LIB_LOCK:
        if _LIB is None:
            path = ctypes.util.find_library("espeak-ng") or "libespeak-ng.so.1"
            try:
                lib = ctypes.CDLL(path)
            except OSError as exc:
                raise TtsError(f"cannot load libespeak-ng ({path}): install the Debian package libespeak-ng1") from exc
            lib.espeak_Initialize.restype = ctypes.c_int
            lib.espeak_Initialize.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_char_p, ctypes.c_int]
            lib.espeak_Synth.argtypes = [
                ctypes.c_void_p,
                ctypes.c_size_t,
                ctypes.c_uint,
                ctypes.c_int,
                ctypes.c_uint,
                ctypes.c_uint,
                ctypes.POINTER(ctypes.c_uint),
                ctypes.c_void_p,
            ]
            lib.espeak_SetVoiceByName.argtypes = [ctypes.c_char_p]
            lib.espeak_SetParameter.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int]
            rate = lib.espeak_Initialize(_AUDIO_OUTPUT_SYNCHRONOUS, 0, None, _INITIALIZE_PHONEME_EVENTS)
            if rate != ESPEAK_RATE_HZ:
                raise TtsError(f"espeak-ng initialised at {rate} Hz, expected {ESPEAK_RATE_HZ}")
            _LIB = lib
        return _LIB


class EspeakTts:
    """Synthesises one sentence at a time; voice, rate (words/min) and pitch (0-100) are fixed per instance."""

    def __init__(self, voice: str = "en-us", rate_wpm: int = 175, pitch: int = 50):
        self._lib = _load_library()
        self.voice, self.rate_wpm, self.pitch = voice, rate_wpm, pitch
        self._chunks: list[np.ndarray] = []
        self._events: list[tuple[int, int, int]] = []  # (sample @22.05k, text_position (1-based chars), length)
        self._callback = _SynthCallback(self._on_synth)  # keep a reference: the library calls it later

    def _on_synth(self, wav, n_samples, events) -> int:
        if n_samples > 0:
            # string_at copies the samples; np.ctypeslib.as_array would create (and cache forever) a new ctypes
            # array type and pointer type for every distinct chunk length: a slow leak over a long conversation.
            self._chunks.append(np.frombuffer(ctypes.string_at(wav, n_samples * 2), dtype=np.int16))
        i = 0
        while events[i].type != _EVENT_LIST_TERMINATED:
            ev = events[i]
            if ev.type == _EVENT_WORD:
                self._events.append((ev.sample, ev.text_position, ev.length))
            i += 1
        return 0

    def synthesize(self, text: str) -> Utterance:
        """Speak `text`; returns 24 kHz PCM and the start sample of each word."""
        encoded = text.encode("utf-8")
        with _LIB_LOCK:
            self._chunks, self._events = [], []
            lib = self._lib
            lib.espeak_SetSynthCallback(self._callback)
            if lib.espeak_SetVoiceByName(self.voice.encode()) != 0:
                raise TtsError(f"espeak-ng has no voice {self.voice!r}")
            lib.espeak_SetParameter(_PARAM_RATE, int(self.rate_wpm), 0)
            lib.espeak_SetParameter(_PARAM_PITCH, int(self.pitch), 0)
            lib.espeak_SetParameter(_PARAM_VOLUME, 100, 0)
            buf = ctypes.create_string_buffer(encoded)
            _LIBC.srand(zlib.crc32(encoded))
            err = lib.espeak_Synth(buf, len(encoded) + 1, 0, _POS_CHARACTER, 0, _CHARS_UTF8, None, None)
            if err != 0:
                raise TtsError(f"espeak_Synth failed with code {err}")
            chunks, events = self._chunks, self._events
        pcm22 = np.concatenate(chunks).astype(np.float32) / 32768.0 if chunks else np.zeros(0, np.float32)
        pcm = resample_poly(pcm22, _RESAMPLE_UP, _RESAMPLE_DOWN).astype(np.float32)  # (N,) @ 24 kHz
        return Utterance(text=text, pcm=pcm, words=tuple(_word_timings(encoded, events, len(pcm22))))


def _word_timings(encoded: bytes, events: list[tuple[int, int, int]], n_samples_22k: int) -> list[WordTiming]:
    """Every word of the text with its start sample at 24 kHz.

    espeak-ng emits no WORD event for some unstressed words it joins to a neighbour ("from the", "I am");
    those get a start interpolated by character position between the surrounding events.
    """
    text = encoded.decode("utf-8")
    words = [(m.start() + 1, m.group()) for m in re.finditer(r"[^\s.,;:!?\"()]+", text)]  # (1-based char pos, word)
    known = {position: sample for sample, position, _ in events}
    anchors = sorted(known.items()) + [(len(text) + 1, n_samples_22k)]
    out = []
    for position, word in words:
        if position in known:
            sample22 = known[position]
        else:
            before = max(((p, smp) for p, smp in anchors if p < position), default=(1, 0))
            after = min((p, smp) for p, smp in anchors if p > position)
            sample22 = before[1] + (after[1] - before[1]) * (position - before[0]) / max(after[0] - before[0], 1)
        out.append(WordTiming(word=word, start_sample=int(round(sample22 * SAMPLE_RATE_HZ / ESPEAK_RATE_HZ))))
    return out
