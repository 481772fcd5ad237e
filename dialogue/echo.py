"""Echo suppression by reference subtraction and gating (loudspeakers instead of headphones).

The agent's own played signal is known. While the agent talks, each microphone block is cross-correlated
with the recent playback to find the echo path's delay and gain (updated only when the match is clear,
i.e. the microphone is dominated by echo). The predicted echo is subtracted, and a block counts as user
speech only when what remains is `margin_db` louder than the predicted echo, so residual echo (reverb,
loudspeaker distortion) cannot trigger barge-in. With no playback, or no echo found, the microphone
passes through unchanged.
"""

import numpy as np

MIN_MATCH_CORRELATION = 0.6
GAIN_SMOOTHING = 0.3
SILENT_REF_RMS = 1e-4


class EchoGate:
    def __init__(self, rate_hz: int, max_delay_s: float, margin_db: float, block_samples: int):
        self.max_delay = int(round(max_delay_s * rate_hz))
        self.block = block_samples
        self.margin_power = 10 ** (margin_db / 10)
        self.reset()

    def reset(self) -> None:
        self._ref = np.zeros(self.max_delay + self.block, np.float32)  # playback history, newest last
        self.gain = 0.0
        self.delay = 0
        self.echo_found = False

    def push_reference(self, played: np.ndarray) -> None:
        """Append the agent audio just sent to the loudspeaker (same rate and block size as the mic)."""
        self._ref = np.concatenate([self._ref[len(played):], np.asarray(played, np.float32)])

    def process(self, mic: np.ndarray) -> tuple[np.ndarray, bool]:
        """mic block (N,) -> (residual (N,), user_dominant): whether the block may count as user speech."""
        n = len(mic)
        if np.sqrt(np.mean(self._ref ** 2)) < SILENT_REF_RMS:
            return mic, True
        self._track_echo_path(mic)
        if not self.echo_found:
            return mic, True
        ref = self._aligned_reference(self.delay, n)
        echo = self.gain * ref
        residual = mic - echo
        user_dominant = float(np.mean(residual ** 2)) > self.margin_power * float(np.mean(echo ** 2)) + 1e-10
        return residual.astype(np.float32), user_dominant

    def _aligned_reference(self, delay: int, n: int) -> np.ndarray:
        end = len(self._ref) - delay
        return self._ref[end - n:end]

    def _track_echo_path(self, mic: np.ndarray) -> None:
        """Cross-correlate mic with every delayed reference block; adopt a clear match."""
        n = len(mic)
        size = 1 << int(np.ceil(np.log2(len(self._ref) + n)))
        corr = np.fft.irfft(np.fft.rfft(self._ref, size) * np.conj(np.fft.rfft(mic, size)), size)
        lags = np.arange(self.max_delay + 1)  # delay d: mic aligns with ref[end-d-n : end-d]
        starts = len(self._ref) - lags - n
        xcorr = corr[starts]  # (D+1,)
        best = int(np.argmax(np.abs(xcorr)))
        ref = self._aligned_reference(best, n)
        denom = np.sqrt(np.sum(ref ** 2) * np.sum(mic ** 2)) + 1e-12
        if abs(xcorr[best]) / denom >= MIN_MATCH_CORRELATION:
            gain = float(xcorr[best] / (np.sum(ref ** 2) + 1e-12))
            self.gain = gain if not self.echo_found else (1 - GAIN_SMOOTHING) * self.gain + GAIN_SMOOTHING * gain
            self.delay, self.echo_found = best, True
