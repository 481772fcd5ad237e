"""What the shipped checkpoints (ecas/checkpoints/gesture_lm, ecas/checkpoints/codecs) produce for a seeded input,
kept in tests/golden/checkpoints.npz and checked by tests/test_golden_checkpoints.py.

Regenerate it after replacing the checkpoints (from the repository root):

    python -m tests.golden.checkpoints

The file holds the seeded conditioning (`text` (N,), `audio` (Q, N)); the float32 generator's sampled `tokens`
(N, K) and decoded `poses` (N, 2, 55, 3), `trans` (N, 2, 3), `expressions` (N, 2, 100); the float32 step path's
guided logits of those tokens, teacher-forced (`logits` (N, K, card+1)); and each codec's float32 streaming
decode of its tokens (`decoded_<region>` (N, 2, F)).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from ecas.core.body import REGIONS
from ecas.core.paths import CHECKPOINTS_DIR
from ecas.core.threads import limit_threads
from gesture.codec.inference import inference_codec
from gesture.codec.model import GestureCodec
from gesture.codec.streaming import StreamingDecoder
from gesture.generator import GestureGenerator
from gesture.lm.checkpoint import load_lm
from gesture.lm.codecs import load_codecs
from gesture.lm.model import GestureLM
from gesture.lm.stepper import LMStepper

REPO = Path(__file__).resolve().parents[2]
LM_DIR, CODEC_DIR = CHECKPOINTS_DIR / "gesture_lm", CHECKPOINTS_DIR / "codecs"
GOLDEN = Path(__file__).with_name("checkpoints.npz")
STEPS, SEED, SPEAKER, CFG_SCALE = 4, 7, 3, 1.3


def load_shipped() -> tuple[GestureLM, dict[str, GestureCodec]]:
    return load_lm(LM_DIR).eval(), load_codecs(CODEC_DIR)


def conditioning(lm: GestureLM) -> tuple[np.ndarray, np.ndarray]:
    """Seeded text tokens (N,) and audio codes (Q, N), with some −1 (no token) among them."""
    rng = np.random.default_rng(SEED)
    spec = lm.spec
    text = rng.integers(-1, spec.text_vocab, STEPS)
    audio = rng.integers(-1, spec.audio_card, (spec.n_audio_codebooks, STEPS))
    return text, audio


def generator(lm: GestureLM, codecs: dict[str, GestureCodec]) -> GestureGenerator:
    return GestureGenerator(lm, codecs, cfg_scale=CFG_SCALE, speaker=SPEAKER, seed=SEED, dtype="float32")


def generate(gen: GestureGenerator, text: np.ndarray, audio: np.ndarray) -> dict:
    """The generator's tokens and motion for the conditioning."""
    steps = [gen.step(int(text[t]), audio[:, t]) for t in range(STEPS)]
    return {
        "tokens": np.stack([s.tokens for s in steps]),
        "poses": np.stack([s.poses for s in steps]),
        "trans": np.stack([s.trans for s in steps]),
        "expressions": np.stack([s.expressions for s in steps]),
    }


@torch.inference_mode()
def lm_logits(stepper: LMStepper, tokens: np.ndarray, text: np.ndarray, audio: np.ndarray) -> np.ndarray:
    """Guided logits (N, K, card+1) of `tokens` (N, K) teacher-forced through a step path."""
    stepper.set_speaker(SPEAKER)
    history = torch.full((tokens.shape[1],), -1)
    out = []
    with stepper.streaming(stepper.batch):
        for t in range(len(tokens)):
            row = [stepper.begin_step(history, int(text[t]), torch.as_tensor(audio[:, t]), CFG_SCALE)]
            row += [stepper.depth_logits(k, int(tokens[t, k]), CFG_SCALE) for k in range(tokens.shape[1] - 1)]
            out.append(torch.stack(row))  # (K, V)
            history = torch.as_tensor(tokens[t])
    return torch.stack(out).numpy()


def decode(codec: GestureCodec, codes: np.ndarray, form: str) -> np.ndarray:
    """codes (N, n_q) of one region -> (N, 2, F) features, streamed through the codec's `form` copy."""
    with StreamingDecoder(inference_codec(codec, form)) as decoder:
        return np.stack([decoder.step(torch.as_tensor(c).view(1, -1, 1))[0].numpy() for c in codes])  # (1, 2, F)


def golden() -> dict[str, np.ndarray]:
    lm, codecs = load_shipped()
    text, audio = conditioning(lm)
    gen = generator(lm, codecs)
    out = {"text": text, "audio": audio, **generate(gen, text, audio)}
    gen.close()
    out["logits"] = lm_logits(LMStepper(lm, guided=True), out["tokens"], text, audio)
    for region in REGIONS:
        out[f"decoded_{region}"] = decode(codecs[region], out["tokens"][:, gen.level_slices[region]], "float32")
    return out


def main() -> int:
    limit_threads()
    np.savez_compressed(GOLDEN, **golden())
    print(f"wrote {GOLDEN.relative_to(REPO)} ({GOLDEN.stat().st_size / 1e3:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
