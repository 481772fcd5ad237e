"""Train the small causal speech tokenizer on espeak-ng voices and the real recordings in ../shared/data.

    nice -n 10 python -m dialogue.train_speech_tokenizer \
        --out ecas/checkpoints/speech_tokenizer/speech_tokenizer.safetensors

Objective: log-mel reconstruction (L1) through an 8-level EMA residual VQ with quantizer dropout,
plus a commitment term. Held out: librivox_0870.wav (real read speech) and unseen espeak sentences.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
import soundfile as sf
import torch
from einops import rearrange
from scipy.signal import resample_poly

from dialogue.speech_tokenizer import DEFAULT_CHECKPOINT, SpeechTokenizer, TokenizerShape
from dialogue.tts import EspeakTts
from ecas.core.paths import REAL_CLIP_ID, data_root
from ecas.core.threads import limit_threads
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES

SHARED_DATA = data_root()
TRAIN_RECORDINGS = (f"beat2/{REAL_CLIP_ID}.wav",)
HELDOUT_RECORDINGS = ("speech/librivox_0870.wav",)
VOICES = (
    "en-us",
    "en",
    "en-us+f3",
    "en-us+m3",
    "en+f2",
    "en-gb-x-rp+m7",
    "en-us+f5",
    "en-us+klatt",
    "en-gb-scotland+m1",
    "en-029+f1",
    "en-us+grandma",
    "en-us+david",
)
HELDOUT_VOICES = ("en-us+f4", "en-gb-x-rp+m5")
EMA_DECAY = 0.99
COMMIT_WEIGHT = 0.25


def load_recording(path: Path) -> np.ndarray:
    pcm, rate = sf.read(str(path), dtype="float32", always_2d=True)
    pcm = pcm.mean(1)
    return resample_poly(pcm, SAMPLE_RATE_HZ, rate).astype(np.float32)


def random_sentences(rng: np.random.Generator, n: int) -> list[str]:
    """Random word sequences from the pocketsphinx dictionary: varied phonetics, natural-ish prosody."""
    import pocketsphinx

    words = [line.split()[0] for line in open(Path(pocketsphinx.get_model_path()) / "en-us" / "cmudict-en-us.dict")]
    words = [w for w in words if w.isalpha() and 2 <= len(w) <= 10]
    endings = (".", "?", "!", ",")
    return [" ".join(rng.choice(words, rng.integers(3, 13))) + endings[rng.integers(len(endings))] for _ in range(n)]


def synthesize_corpus(rng: np.random.Generator, voices, n_sentences: int) -> np.ndarray:
    """espeak-ng sentences with random voice, rate and pitch, separated by short silences."""
    pieces = []
    for sentence in random_sentences(rng, n_sentences):
        tts = EspeakTts(
            voice=str(rng.choice(voices)), rate_wpm=int(rng.integers(120, 230)), pitch=int(rng.integers(15, 90))
        )
        pieces += [tts.synthesize(sentence).pcm, np.zeros(int(rng.integers(0, SAMPLE_RATE_HZ // 2)), np.float32)]
    return np.concatenate(pieces)


def random_crops(rng, sources: list[np.ndarray], batch: int, steps: int) -> torch.Tensor:
    """(B, steps*1920) crops with random gain and occasional background noise."""
    n = steps * STEP_SAMPLES
    weights = np.array([len(s) for s in sources], float)
    crops = []
    for _ in range(batch):
        src = sources[rng.choice(len(sources), p=weights / weights.sum())]
        start = rng.integers(0, len(src) - n)
        crop = src[start : start + n] * rng.uniform(0.1, 1.5) / max(np.abs(src[start : start + n]).max(), 1e-3)
        if rng.random() < 0.3:
            crop = crop + rng.standard_normal(n).astype(np.float32) * 10 ** rng.uniform(-4, -1.5)
        crops.append(np.clip(crop, -1, 1))
    return torch.from_numpy(np.stack(crops)).float()


class EmaRvqTrainer:
    """Quantises with straight-through gradients and updates each level's codebook as an EMA of cluster means."""

    def __init__(self, model: SpeechTokenizer, rng: np.random.Generator):
        q, k, d = model.rvq.codebooks.shape
        self.model, self.rng = model, rng
        self.counts = torch.ones(q, k)
        self.sums = model.rvq.codebooks.clone()
        self.initialised = False

    def quantize(self, z: torch.Tensor, n_levels: int) -> tuple[torch.Tensor, torch.Tensor]:
        """z (N, D) -> straight-through quantised (N, D) and commitment loss; updates codebooks from all 8 levels."""
        books = self.model.rvq.codebooks
        residual = z.detach()
        if not self.initialised:
            self._init_from(residual)
        quantised = torch.zeros_like(residual)
        kept = torch.zeros_like(residual)
        for level in range(books.shape[0]):
            dist = residual.pow(2).sum(-1, keepdim=True) - 2 * residual @ books[level].T + books[level].pow(2).sum(-1)
            idx = dist.argmin(-1)  # (N,)
            self._ema_update(level, residual, idx)
            chosen = books[level][idx]
            quantised = quantised + chosen
            if level < n_levels:
                kept = quantised.clone()
            residual = residual - chosen
        commit = (z - kept).pow(2).mean()
        return z + (kept - z).detach(), commit

    def _init_from(self, residual: torch.Tensor) -> None:
        """Initialise each level from random residual vectors of the first batch."""
        books = self.model.rvq.codebooks
        r = residual
        for level in range(books.shape[0]):
            books[level] = r[torch.from_numpy(self.rng.choice(len(r), books.shape[1], replace=len(r) < books.shape[1]))]
            dist = r.pow(2).sum(-1, keepdim=True) - 2 * r @ books[level].T + books[level].pow(2).sum(-1)
            r = r - books[level][dist.argmin(-1)]
        self.sums = books.clone()
        self.initialised = True

    def _ema_update(self, level: int, residual: torch.Tensor, idx: torch.Tensor) -> None:
        books = self.model.rvq.codebooks
        onehot = torch.nn.functional.one_hot(idx, books.shape[1]).float()  # (N, K)
        self.counts[level] = EMA_DECAY * self.counts[level] + (1 - EMA_DECAY) * onehot.sum(0)
        self.sums[level] = EMA_DECAY * self.sums[level] + (1 - EMA_DECAY) * onehot.T @ residual
        books[level] = self.sums[level] / self.counts[level].clamp(min=1e-5)[:, None]
        dead = self.counts[level] < 0.1 * len(idx) / books.shape[1] * (1 - EMA_DECAY) * 10
        if dead.any():
            replace = residual[torch.from_numpy(self.rng.integers(0, len(residual), int(dead.sum())))]
            books[level][dead] = replace
            self.sums[level][dead] = replace
            self.counts[level][dead] = 1.0


def reconstruction_l1(model: SpeechTokenizer, pcm: np.ndarray, n_levels: int) -> float:
    """Mean absolute log-mel error when decoding the first n_levels codes of a whole recording."""
    n_steps = len(pcm) // STEP_SAMPLES
    x = torch.from_numpy(pcm[: n_steps * STEP_SAMPLES])[None]
    with torch.no_grad():
        feats = model.step_features(torch.nn.functional.pad(x, (model.history_samples(), 0)))  # (1, S, F*M)
        codes = model.encode(x)  # (1, Q, S)
        latent_q = model.rvq.decode(rearrange(codes, "b q s -> (b s) q"), n_levels)[None]  # (1, S, D)
        return float((model.decode_features(latent_q) - feats).abs().mean())


def mean_baseline_l1(model: SpeechTokenizer, pcm: np.ndarray) -> float:
    """Error of predicting each band's mean: the floor any useful code must beat."""
    x = torch.from_numpy(pcm[: len(pcm) // STEP_SAMPLES * STEP_SAMPLES])[None]
    feats = model.step_features(torch.nn.functional.pad(x, (model.history_samples(), 0)))
    return float((feats - feats.mean(1, keepdim=True)).abs().mean())


def code_perplexity(model: SpeechTokenizer, pcm: np.ndarray) -> list[float]:
    codes = model.encode(torch.from_numpy(pcm[: len(pcm) // STEP_SAMPLES * STEP_SAMPLES])[None])[0]  # (Q, S)
    out = []
    for level_codes in codes:
        p = torch.bincount(level_codes, minlength=model.shape.bins).float()
        p = p / p.sum()
        out.append(float(torch.exp(-(p[p > 0] * p[p > 0].log()).sum())))
    return out


def train(out: Path, iterations: int, n_sentences: int, seed: int, batch: int, steps: int, lr: float) -> dict:
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    t0 = time.time()
    sources = [synthesize_corpus(rng, VOICES, n_sentences)]
    sources += [load_recording(SHARED_DATA / p) for p in TRAIN_RECORDINGS]
    heldout = {
        "librivox_0870 (real, held out)": load_recording(SHARED_DATA / HELDOUT_RECORDINGS[0]),
        "espeak (unseen voices and sentences)": synthesize_corpus(np.random.default_rng(seed + 1), HELDOUT_VOICES, 20),
    }
    model = SpeechTokenizer(TokenizerShape())
    rvq = EmaRvqTrainer(model, rng)
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=0.0)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=iterations, pct_start=0.05)
    for it in range(iterations):
        x = random_crops(rng, sources, batch, steps)
        feats = model.step_features(torch.nn.functional.pad(x, (model.history_samples(), 0)))  # (B, S, F*M)
        latent, _ = model.encode_latent(feats)
        n_levels = int(rng.integers(1, model.shape.n_q + 1)) if rng.random() < 0.5 else model.shape.n_q
        zq, commit = rvq.quantize(rearrange(latent, "b s d -> (b s) d"), n_levels)
        recon = model.decode_features(rearrange(zq, "(b s) d -> b s d", b=batch))
        loss = (recon - feats).abs().mean() + COMMIT_WEIGHT * commit
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        opt.step()
        sched.step()
        if it % 200 == 0 or it == iterations - 1:
            print(f"it {it} loss {loss.item():.4f} commit {commit.item():.4f} ({time.time() - t0:.0f} s)", flush=True)
    model.eval()
    metrics = {
        name: {
            "mel_l1_8_levels": reconstruction_l1(model, pcm, 8),
            "mel_l1_1_level": reconstruction_l1(model, pcm, 1),
            "mel_l1_band_mean_baseline": mean_baseline_l1(model, pcm),
            "code_perplexity_per_level": [round(p, 1) for p in code_perplexity(model, pcm)],
        }
        for name, pcm in heldout.items()
    }
    info = {
        "iterations": iterations,
        "batch": batch,
        "crop_steps": steps,
        "lr": lr,
        "seed": seed,
        "n_espeak_sentences": n_sentences,
        "train_audio_s": round(sum(len(s) for s in sources) / SAMPLE_RATE_HZ, 1),
        "wall_time_s": round(time.time() - t0, 1),
        "metrics": metrics,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    model.save(out, {"training": info})
    print(json.dumps(info, indent=2))
    return info


def main(argv=None) -> None:
    limit_threads()
    p = argparse.ArgumentParser(prog="ecas train-speech-tokenizer", description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=DEFAULT_CHECKPOINT)
    p.add_argument("--iterations", type=int, default=3000)
    p.add_argument("--sentences", type=int, default=600)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--crop-steps", type=int, default=25)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    train(a.out, a.iterations, a.sentences, a.seed, a.batch, a.crop_steps, a.lr)


if __name__ == "__main__":
    main()
