"""The local backend's text vocabulary: every word hashes into one of 8192 buckets.

A word is lower-cased and stripped of everything but letters, digits and apostrophes; its id is
blake2b(word) mod 8192. No word list to ship, stable across runs and machines, and any recogniser's or
TTS's word maps to a valid id; collisions (rare for a conversational vocabulary) only merge two words.
"""

import hashlib
import re

from ecas.core.spec import ConditionSpec

TEXT_VOCAB_SIZE = 8192
SPEECH_CODE_BINS = 256
LOCAL_EMBED_DIM = 256
LOCAL_SPEC = ConditionSpec(
    name="local-v1", text_vocab=TEXT_VOCAB_SIZE, audio_card=SPEECH_CODE_BINS, embed_dim=LOCAL_EMBED_DIM
)
_NON_WORD = re.compile(r"[^a-z0-9']+")


def normalize_word(word: str) -> str:
    return _NON_WORD.sub("", word.lower()).strip("'")


def word_token(word: str) -> int:
    """A word's text token id in [0, TEXT_VOCAB_SIZE), or -1 for an empty word."""
    norm = normalize_word(word)
    if not norm:
        return -1
    digest = hashlib.blake2b(norm.encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") % TEXT_VOCAB_SIZE
