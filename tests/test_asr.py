"""Streaming pocketsphinx: partial then final hypotheses with word times, and forced alignment."""

import numpy as np

from dialogue.alignment import align_text
from dialogue.asr import StreamingAsr
from dialogue.resample import StreamResampler
from tests.dialogue_helpers import LIBRIVOX, load_24k

REFERENCE = set(LIBRIVOX.with_suffix(".txt").read_text().lower().split())


def test_streaming_recognition_gives_partials_then_timed_words():
    speech = StreamResampler(24_000, 16_000).process(load_24k(LIBRIVOX))
    asr = StreamingAsr()
    asr.begin(10.0, speech[:1280])
    partials, final = [], None
    for i in range(1280, len(speech), 1280):
        asr.feed(speech[i : i + 1280])
        assert asr.advance() is None
        partials.append(asr.partial)
    asr.finish()
    for _ in range(10):
        final = final or asr.advance()
    assert final is not None and not asr.active
    assert any(partials[len(partials) // 2]) and len(partials[-1].split()) > len(partials[10].split())
    words = [w.word for w in final]
    assert len(set(words) & REFERENCE) >= 0.6 * len(REFERENCE)
    assert all(10.0 <= w.start_s < w.end_s <= 10.0 + len(speech) / 16_000 + 0.1 for w in final)
    assert [w.start_s for w in final] == sorted(w.start_s for w in final)


def test_backlog_is_decoded_within_the_budget():
    asr = StreamingAsr(budget_samples=1920)
    asr.begin(0.0, np.zeros(16_000, np.float32))  # a 1 s pre-roll
    asr.finish()
    results = [asr.advance() for _ in range(12)]
    assert all(r is None for r in results[:8]) and results[8] == []  # 16000 / 1920 samples per call: the 9th finishes


def test_forced_alignment_recovers_the_transcript_words_and_times():
    speech = load_24k(LIBRIVOX)
    words = align_text(LIBRIVOX.with_suffix(".txt").read_text(), speech, 24_000)
    assert [w.word for w in words] == LIBRIVOX.with_suffix(".txt").read_text().lower().split()
    assert words[0].start_s < 0.5 and 6.0 < words[-1].end_s < 7.2
