"""A small causal speech tokenizer: 24 kHz audio -> 8 residual-VQ codes per 80 ms step.

Front end: causal log-mel (40 ms window, 20 ms hop, 4 frames per step, 64 bands).
Encoder: per-step linear + GRU + projection to a 64-d latent, quantised by an 8-level residual VQ.
Decoder (training objective and quality metric): GRU that reconstructs the step's 4 log-mel frames.

`SpeechTokenizer` is stateless (offline, whole sequences); `StreamingSpeechEncoder` carries the audio
tail and the GRU state across steps and gives the same codes one step at a time.
"""

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from einops import rearrange
from safetensors.torch import load_file, save_file
from torch import nn

from ecas.core.mel import mel_filterbank
from ecas.core.paths import CHECKPOINTS_DIR
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_SAMPLES

DEFAULT_CHECKPOINT = CHECKPOINTS_DIR / "speech_tokenizer" / "speech_tokenizer.safetensors"


@dataclass(frozen=True)
class TokenizerShape:
    n_mels: int = 64
    hop_samples: int = 480  # 20 ms
    window_samples: int = 960  # 40 ms
    hidden: int = 256
    latent: int = 64
    n_q: int = 8
    bins: int = 256

    @property
    def frames_per_step(self) -> int:
        return STEP_SAMPLES // self.hop_samples


class CausalLogMel(nn.Module):
    """Log-mel frames; frame i covers samples [(i+1)*hop - window, (i+1)*hop)."""

    def __init__(self, shape: TokenizerShape):
        super().__init__()
        self.shape = shape
        mel = mel_filterbank(SAMPLE_RATE_HZ, shape.window_samples, shape.n_mels, fmin_hz=50, fmax_hz=8000)
        self.register_buffer("mel_basis", torch.from_numpy(mel).float(), persistent=False)  # (M, F)
        self.register_buffer("window", torch.hann_window(shape.window_samples), persistent=False)

    def forward(self, padded: torch.Tensor) -> torch.Tensor:
        """padded (B, window - hop + N) -> (B, N // hop, M); the first window - hop samples are history."""
        frames = padded.unfold(-1, self.shape.window_samples, self.shape.hop_samples)  # (B, T, W)
        spec = torch.fft.rfft(frames * self.window).abs() ** 2  # (B, T, F)
        return torch.log(spec @ self.mel_basis.T + 1e-5)  # (B, T, M)


class ResidualVQ(nn.Module):
    """n_q codebooks of `bins` vectors; codebook vectors are EMA cluster means (updated by the trainer)."""

    def __init__(self, n_q: int, bins: int, dim: int):
        super().__init__()
        self.register_buffer("codebooks", torch.randn(n_q, bins, dim) * 0.1)  # (Q, K, D)

    def encode(self, z: torch.Tensor) -> torch.Tensor:
        """z (N, D) -> codes (N, Q)."""
        residual, codes = z, []
        for book in self.codebooks:  # (K, D)
            dist = residual.pow(2).sum(-1, keepdim=True) - 2 * residual @ book.T + book.pow(2).sum(-1)  # (N, K)
            idx = dist.argmin(-1)
            codes.append(idx)
            residual = residual - book[idx]
        return torch.stack(codes, -1)

    def decode(self, codes: torch.Tensor, n_levels: int | None = None) -> torch.Tensor:
        """codes (N, Q) -> (N, D), summing the first n_levels levels."""
        n_levels = codes.shape[-1] if n_levels is None else n_levels
        return sum(self.codebooks[q][codes[..., q]] for q in range(n_levels))


class SpeechTokenizer(nn.Module):
    """Stateless model; `encode` works on whole sequences of steps."""

    def __init__(self, shape: TokenizerShape = TokenizerShape()):
        super().__init__()
        self.shape = shape
        step_feats = shape.n_mels * shape.frames_per_step
        self.mel = CausalLogMel(shape)
        self.enc_in = nn.Sequential(nn.Linear(step_feats, shape.hidden), nn.GELU())
        self.enc_rnn = nn.GRU(shape.hidden, shape.hidden, batch_first=True)
        self.enc_out = nn.Linear(shape.hidden, shape.latent)
        self.rvq = ResidualVQ(shape.n_q, shape.bins, shape.latent)
        self.dec_rnn = nn.GRU(shape.latent, shape.hidden, batch_first=True)
        self.dec_out = nn.Linear(shape.hidden, step_feats)

    def history_samples(self) -> int:
        return self.shape.window_samples - self.shape.hop_samples

    def step_features(self, padded: torch.Tensor) -> torch.Tensor:
        """padded audio (B, history + S*STEP) -> per-step log-mel stacks (B, S, frames*M)."""
        mel = self.mel(padded)  # (B, S*F, M)
        return rearrange(mel, "b (s f) m -> b s (f m)", f=self.shape.frames_per_step)

    def encode_latent(self, feats: torch.Tensor, hidden: torch.Tensor | None = None):
        """feats (B, S, F*M) -> latent (B, S, D), GRU state (1, B, H)."""
        h, hidden = self.enc_rnn(self.enc_in(feats), hidden)
        return self.enc_out(h), hidden

    def decode_features(self, latent_q: torch.Tensor) -> torch.Tensor:
        """quantised latent (B, S, D) -> reconstructed log-mel stacks (B, S, F*M)."""
        return self.dec_out(self.dec_rnn(latent_q)[0])

    @torch.no_grad()
    def encode(self, pcm: torch.Tensor) -> torch.Tensor:
        """pcm (B, S*1920) at 24 kHz -> codes (B, 8, S), starting from silence history."""
        padded = nn.functional.pad(pcm, (self.history_samples(), 0))
        latent, _ = self.encode_latent(self.step_features(padded))  # (B, S, D)
        codes = self.rvq.encode(rearrange(latent, "b s d -> (b s) d"))  # (B*S, Q)
        return rearrange(codes, "(b s) q -> b q s", b=pcm.shape[0])

    def save(self, path: Path, metadata: dict | None = None) -> None:
        meta = {"shape": json.dumps(asdict(self.shape))}
        meta.update({k: json.dumps(v) for k, v in (metadata or {}).items()})
        save_file({k: v.contiguous() for k, v in self.state_dict().items()}, str(path), metadata=meta)

    @classmethod
    def load(cls, path: Path | str) -> "SpeechTokenizer":
        from safetensors import safe_open

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(
                f"speech tokenizer checkpoint not found: {path} "
                "(train one with `python -m dialogue.train_speech_tokenizer`)"
            )
        with safe_open(str(path), "pt") as f:
            shape = TokenizerShape(**json.loads(f.metadata()["shape"]))
        model = cls(shape)
        model.load_state_dict(load_file(str(path)))
        return model.eval()


class StreamingSpeechEncoder:
    """Streaming state over a `SpeechTokenizer`: the last window-hop samples and the encoder GRU state."""

    def __init__(self, model: SpeechTokenizer):
        self.model = model
        self.reset()

    def reset(self) -> None:
        self._history = torch.zeros(1, self.model.history_samples())
        self._hidden: torch.Tensor | None = None

    @torch.no_grad()
    def step(self, pcm: np.ndarray) -> np.ndarray:
        """pcm (1920,) float32 -> codes (8,) int32."""
        if pcm.shape != (STEP_SAMPLES,):
            raise ValueError(f"speech tokenizer step expects ({STEP_SAMPLES},) samples, got {pcm.shape}")
        padded = torch.cat([self._history, torch.from_numpy(np.ascontiguousarray(pcm, np.float32))[None]], -1)
        self._history = padded[:, -self.model.history_samples() :]
        latent, self._hidden = self.model.encode_latent(self.model.step_features(padded), self._hidden)  # (1, 1, D)
        return self.model.rvq.encode(latent[0]).reshape(-1).numpy().astype(np.int32)
