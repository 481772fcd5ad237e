"""What a dialogue backend emits each step, and therefore what a gesture LM is conditioned on."""

from dataclasses import dataclass

N_AUDIO_CODEBOOKS = 8


@dataclass(frozen=True)
class ConditionSpec:
    """Vocabulary of the conditioning tokens: one text token and 8 audio codes per step."""

    name: str
    text_vocab: int
    audio_card: int
    embed_dim: int
    n_audio_codebooks: int = N_AUDIO_CODEBOOKS

    def check_compatible(self, other: "ConditionSpec", what: str) -> None:
        """Raise a clear error when a model trained on `self` is fed by a backend emitting `other`."""
        if self != other:
            raise SpecMismatchError(
                f"{what}: the gesture model was trained on condition spec {self}, "
                f"but the dialogue backend emits {other}. Use a gesture checkpoint trained for this backend."
            )

    def to_dict(self) -> dict:
        return dict(
            name=self.name,
            text_vocab=self.text_vocab,
            audio_card=self.audio_card,
            embed_dim=self.embed_dim,
            n_audio_codebooks=self.n_audio_codebooks,
        )

    @classmethod
    def from_dict(cls, d: dict) -> "ConditionSpec":
        return cls(**d)


class SpecMismatchError(RuntimeError):
    pass


MOSHI_SPEC = ConditionSpec(name="moshi", text_vocab=32001, audio_card=2049, embed_dim=4096)
