"""The local text vocabulary: hashed words, pinned ids, and the condition spec it defines."""

from dialogue.text_vocab import LOCAL_SPEC, TEXT_VOCAB_SIZE, normalize_word, word_token
from ecas.core.spec import ConditionSpec


def test_pinned_ids_never_change():
    # Gesture checkpoints trained on the local backend depend on these: never change the hash.
    assert [word_token(w) for w in ("hello", "don't", "dashwood")] == [5799, 3404, 8021]


def test_normalisation_and_empty_words():
    assert word_token("Hello!") == word_token("hello") == word_token("'HELLO'")
    assert normalize_word("Don't,") == "don't"
    assert word_token("") == word_token("...") == -1


def test_ids_are_in_range_and_mostly_distinct():
    words = [f"word{i}" for i in range(500)]
    ids = [word_token(w) for w in words]
    assert all(0 <= i < TEXT_VOCAB_SIZE for i in ids)
    assert len(set(ids)) > 0.95 * len(ids)


def test_local_spec():
    assert LOCAL_SPEC == ConditionSpec(name="local-v1", text_vocab=8192, audio_card=256, embed_dim=256)
