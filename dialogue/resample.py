"""Causal streaming polyphase resampling (e.g. 24 kHz -> 16 kHz for the VAD and ASR)."""

from math import gcd

import numpy as np
from scipy.signal import firwin, upfirdn


def lowpass_taps(up: int, down: int) -> np.ndarray:
    """Kaiser-windowed anti-aliasing filter at the upsampled rate, gain `up`."""
    half_len = 10 * max(up, down)
    return (firwin(2 * half_len + 1, 1.0 / max(up, down), window=("kaiser", 5.0)) * up).astype(np.float64)


class StreamResampler:
    """Resamples blocks of any length; block-by-block output equals whole-signal output exactly.

    Output sample m sits at upsampled position m*down and depends only on input up to that position,
    so the resampler is causal, with a group delay of (len(taps) - 1) / 2 upsampled samples.
    """

    def __init__(self, in_rate_hz: int, out_rate_hz: int):
        g = gcd(in_rate_hz, out_rate_hz)
        self.up, self.down = out_rate_hz // g, in_rate_hz // g
        self.taps = lowpass_taps(self.up, self.down)
        self._history_samples = -(-len(self.taps) // self.up) + self.down  # inputs any new output can reach back to
        self.reset()

    def reset(self) -> None:
        self._tail = np.zeros(0, np.float64)  # last input samples, starting at global index self._tail_start
        self._tail_start = 0
        self._n_in = 0
        self._n_out = 0

    def process(self, block: np.ndarray) -> np.ndarray:
        """block (N,) -> (M,) float32, M such that the running output count is floor((n_in - 1) * up / down) + 1."""
        block = np.asarray(block, np.float64).reshape(-1)
        if block.size == 0:
            return np.zeros(0, np.float32)
        x = np.concatenate([self._tail, block])  # starts at global input index self._tail_start
        self._n_in += block.size
        n_ready = (self._n_in - 1) * self.up // self.down + 1
        y = upfirdn(self.taps, x, self.up, self.down)  # local output 0 = global output tail_start*up/down
        first_local = self._n_out - self._tail_start * self.up // self.down
        out = y[first_local : first_local + n_ready - self._n_out]
        self._n_out = n_ready
        self._keep_tail(x)
        return out.astype(np.float32)

    def _keep_tail(self, x: np.ndarray) -> None:
        """Keep enough input for the next outputs; the tail start stays a multiple of `down` so phases align."""
        new_start = max(0, self._n_in - self._history_samples)
        new_start -= new_start % self.down
        self._tail = x[new_start - self._tail_start :]
        self._tail_start = new_start
