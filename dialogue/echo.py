"""Echo gating against the agent's known playback (loudspeakers instead of headphones).

A double-talk detector in the Geigel family, with a learned echo return: the agent's played signal is
known, so for each microphone block the loudest the echo could be is `coupling × (the highest short-time
RMS of the playback over every delay up to max_delay)`. `coupling` (mic RMS / that highest playback RMS) is learned
from blocks where the mic clearly is the playback (normalised cross-correlation ≥ 0.6 at some delay,
playback above -40 dBFS),
jumping up at once and decaying slowly. A block counts as user speech only when the mic is `margin_db`
above that bound; otherwise the VAD sees silence, so the agent's own voice (even with room reverberation)
cannot barge in, while a user talking over it louder than the echo still can. With no playback, or no echo
ever heard (headphones), the microphone passes unchanged.
"""

import numpy as np

MIN_MATCH_CORRELATION = 0.6
MIN_LEARN_REF_RMS = 0.01  # learn the coupling only from clearly audible playback
COUPLING_DECAY_PER_BLOCK = 0.995  # about 8 s to halve at 80 ms blocks
SILENT_REF_RMS = 1e-4


class EchoGate:
    def __init__(self, rate_hz: int, max_delay_s: float, margin_db: float, block_samples: int):
        self.max_delay = int(round(max_delay_s * rate_hz))
        self.block = block_samples
        self.margin = 10 ** (margin_db / 20)
        self.reset()

    def reset(self) -> None:
        self._ref = np.zeros(self.max_delay + self.block, np.float32)  # playback history, newest last
        self.coupling = 0.0

    def push_reference(self, played: np.ndarray) -> None:
        """Append the agent audio just sent to the loudspeaker (same rate as the mic)."""
        self._ref = np.concatenate([self._ref[len(played) :], np.asarray(played, np.float32)])

    def process(self, mic: np.ndarray) -> tuple[np.ndarray, bool]:
        """mic block (N,) -> (mic, user_dominant): whether the block may count as user speech."""
        n = len(mic)
        ref_rms = self._windowed_rms(n)  # (D+1,) playback RMS aligned with the block, per delay
        if ref_rms.max() < SILENT_REF_RMS:
            return mic, True
        self._learn_coupling(mic, ref_rms)
        mic_rms = float(np.sqrt(np.mean(mic.astype(np.float64) ** 2)))
        return mic, mic_rms > self.margin * self.coupling * float(ref_rms.max())

    def _windowed_rms(self, n: int) -> np.ndarray:
        """RMS of ref[end-d-n : end-d] for every delay d in 0..max_delay (cumulative sums)."""
        energy = np.concatenate([[0.0], np.cumsum(self._ref.astype(np.float64) ** 2)])
        ends = len(self._ref) - np.arange(self.max_delay + 1)
        return np.sqrt(np.maximum(energy[ends] - energy[ends - n], 0.0) / n)

    def _learn_coupling(self, mic: np.ndarray, ref_rms: np.ndarray) -> None:
        n = len(mic)
        self.coupling *= COUPLING_DECAY_PER_BLOCK
        if ref_rms.max() < MIN_LEARN_REF_RMS:
            return
        size = 1 << int(np.ceil(np.log2(len(self._ref) + n)))
        corr = np.fft.irfft(np.fft.rfft(self._ref, size) * np.conj(np.fft.rfft(mic, size)), size)
        starts = len(self._ref) - np.arange(self.max_delay + 1) - n  # delay d: mic aligns with ref[start:start+n]
        mic_rms = float(np.sqrt(np.mean(mic.astype(np.float64) ** 2)))
        normalised = np.abs(corr[starts]) / (n * ref_rms * mic_rms + 1e-12)
        normalised[ref_rms < 0.1 * ref_rms.max()] = 0.0  # near-silent playback windows match by accident
        best = int(np.argmax(normalised))
        if normalised[best] >= MIN_MATCH_CORRELATION:
            self.coupling = max(self.coupling, mic_rms / float(ref_rms.max()))
