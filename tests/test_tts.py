"""espeak-ng through libespeak-ng: 24 kHz audio and the start sample of every word."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dialogue.speaker import Speaker
from dialogue.transcript import Transcript
from dialogue.tts import EspeakTts, TtsError

SENTENCE = "Hello there, the weather is lovely today."


def test_words_in_order_with_increasing_samples_inside_the_audio():
    utt = EspeakTts("en-us").synthesize(SENTENCE)
    assert [w.word for w in utt.words] == ["Hello", "there", "the", "weather", "is", "lovely", "today"]
    starts = [w.start_sample for w in utt.words]
    assert starts == sorted(starts) and starts[0] < 2400 and starts[-1] < len(utt.pcm)
    assert utt.pcm.dtype == np.float32 and 1.5 < len(utt.pcm) / 24_000 < 4.0


def test_word_starts_match_the_audio_energy():
    utt = EspeakTts("en-us").synthesize(SENTENCE)
    for w in utt.words[1:]:  # voiced energy within 150 ms after each word start
        window = utt.pcm[w.start_sample : w.start_sample + 3600]
        assert np.sqrt(np.mean(window**2)) > 0.02, w


def test_rate_and_voice_change_the_audio():
    slow = EspeakTts("en-us", rate_wpm=120).synthesize(SENTENCE)
    fast = EspeakTts("en-us", rate_wpm=260).synthesize(SENTENCE)
    assert len(slow.pcm) > 1.5 * len(fast.pcm)
    other = EspeakTts("en-us+f3", pitch=80).synthesize(SENTENCE)
    assert not np.allclose(other.pcm[:4800], slow.pcm[:4800])


def test_unknown_voice_is_a_clear_error():
    with pytest.raises(TtsError, match="no voice 'xx-nope'"):
        EspeakTts("xx-nope").synthesize("hi")


def test_speaker_streams_1920_samples_and_places_tokens_at_word_starts():
    tts = EspeakTts("en-us")
    transcript = Transcript("t")
    speaker = Speaker(transcript, tts.synthesize)
    speaker.begin_reply()
    speaker.say("Good morning. How are you?")
    speaker.end_reply()
    steps = [speaker.step(i * 0.08) for i in range(60)]
    assert all(s.pcm.shape == (1920,) for s in steps)
    pieces = [(i, s.text_piece) for i, s in enumerate(steps) if s.text_piece]
    assert [p for _, p in pieces] == ["Good", "morning", "How", "are", "you"]
    (turn,) = transcript.turns
    assert not speaker.busy and turn.end_s > turn.words[-1].start_s
    for (i, _), word in zip(pieces, turn.words):
        assert int(word.start_s / 0.08 + 1e-9) <= i <= int(word.start_s / 0.08) + 1


def test_words_espeak_joins_to_a_neighbour_still_get_a_start():
    utt = EspeakTts("en-us").synthesize("Hello from the test server. I am fine.")
    assert [w.word for w in utt.words] == ["Hello", "from", "the", "test", "server", "I", "am", "fine"]
    starts = [w.start_sample for w in utt.words]
    assert starts == sorted(starts) and len(set(starts)) == len(starts)


def test_the_same_sentence_gives_the_same_samples_whatever_else_draws_from_rand():
    """The default voice's breath noise uses libc rand(), which other libraries in the process draw from too (this
    made offline runs differ). Two fresh processes, one of which draws from rand() first, synthesise the same."""
    script = (
        "import ctypes, hashlib, sys; from dialogue.tts import EspeakTts; tts = EspeakTts('en-us+f3'); "
        "tts.synthesize('Hello.'); [ctypes.CDLL(None).rand() for _ in range(int(sys.argv[1]))]; "
        "print(hashlib.md5(tts.synthesize('That sounds important.').pcm.tobytes()).hexdigest())"
    )
    digests = {
        subprocess.run(
            [sys.executable, "-c", script, str(draws)],
            capture_output=True,
            text=True,
            check=True,
            cwd=Path(__file__).resolve().parents[1],
        ).stdout
        for draws in (0, 17)
    }
    assert len(digests) == 1
