"""The user side of every backend: 24k -> 16k, echo gate, Silero VAD + turn state machine, streaming ASR."""

from dataclasses import dataclass, field

import numpy as np

from dialogue.asr import RecognizedWord, StreamingAsr
from dialogue.config import AsrConfig, EchoConfig, TurnConfig, VadConfig
from dialogue.echo import EchoGate
from dialogue.resample import StreamResampler
from dialogue.vad import VAD_CHUNK_S, VAD_RATE_HZ, SileroVad, VadEvent, VadStateMachine
from ecas.core.messages import VadState
from ecas.core.timing import SAMPLE_RATE_HZ, STEP_S, STEP_SAMPLES

STEP_16K = STEP_SAMPLES * VAD_RATE_HZ // SAMPLE_RATE_HZ  # 1280
PREROLL_S = 0.3  # audio before the VAD's speech start that the recogniser also hears
HISTORY_S = 1.5  # 16 kHz audio kept for the pre-roll


@dataclass
class Heard:
    """What the listener made of one step of user audio."""

    vad_prob: float
    vad_state: VadState
    speech_run_s: float  # how long the user has been talking continuously (0 when quiet)
    partial: str
    events: list[VadEvent] = field(default_factory=list)
    final_words: list[RecognizedWord] | None = None  # set on the step an utterance's recognition completes
    turn_start_s: float = 0.0
    turn_end_s: float = 0.0


class UserListener:
    def __init__(self, vad: VadConfig, echo: EchoConfig, asr: AsrConfig | None, turn: TurnConfig | None = None):
        self.resample_user = StreamResampler(SAMPLE_RATE_HZ, VAD_RATE_HZ)
        self.resample_agent = StreamResampler(SAMPLE_RATE_HZ, VAD_RATE_HZ)
        self.vad = SileroVad()
        self.turns = VadStateMachine.from_config(vad, turn)  # turn None: the turn ends after vad.stop_s of silence
        self.echo = EchoGate(VAD_RATE_HZ, echo.max_delay_s, echo.margin_db, STEP_16K) if echo.mode == "gate" else None
        self.asr = (
            None
            if asr is None
            else StreamingAsr(
                asr.hmm,
                asr.lm,
                asr.dict,
                budget_samples=int(asr.budget_steps * STEP_16K),
                max_hmm_per_frame=asr.max_hmm_per_frame,
                max_words_per_frame=asr.max_words_per_frame,
                phone_lookahead_frames=asr.phone_lookahead_frames,
            )
        )
        self.reset()

    def reset(self) -> None:
        for part in (self.resample_user, self.resample_agent, self.vad, self.turns, self.echo, self.asr):
            if part is not None:
                part.reset()
        self._history = np.zeros(int(HISTORY_S * VAD_RATE_HZ), np.float32)
        self._t_s = 0.0  # stream time at the end of the audio heard so far
        self._chunk_t_s = 0.0
        self._prob = 0.0
        self._run_start_s: float | None = None
        self._turn_start_s = 0.0
        self._turn_end_s = 0.0

    def skip(self, seconds: float) -> None:
        """Advance the stream clock over dropped input, so later events keep their true times."""
        self._t_s += seconds
        self._chunk_t_s += seconds
        self.turns.skip(seconds)

    def step(self, user_pcm: np.ndarray, agent_pcm_played: np.ndarray | None) -> Heard:
        """user_pcm (1920,) @ 24 kHz; agent_pcm_played: what the loudspeaker played in the previous step."""
        mic = self.resample_user.process(user_pcm)  # (1280,) @ 16 kHz
        user_dominant = True
        if self.echo is not None:
            if agent_pcm_played is not None:
                self.echo.push_reference(self.resample_agent.process(agent_pcm_played))
            mic, user_dominant = self.echo.process(mic)
        self._history = np.concatenate([self._history[len(mic) :], mic])
        self.turns.hear(mic)
        self._t_s += len(mic) / VAD_RATE_HZ
        events = []
        already_listening = self.asr is not None and self.asr.active  # a new utterance's pre-roll holds this block
        for prob in self.vad.process(mic):
            self._prob = prob if user_dominant else 0.0
            self._chunk_t_s += VAD_CHUNK_S
            event = self.turns.update(self._prob)
            self._track_speech_run()
            if event is not None:
                events.append(event)
                self._on_event(event)
        if already_listening:
            self.asr.feed(mic)
        final = self.asr.advance() if self.asr is not None else None
        return Heard(
            vad_prob=self._prob,
            vad_state=self.turns.state,
            speech_run_s=0.0 if self._run_start_s is None else self._chunk_t_s - self._run_start_s,
            partial=self.asr.partial if self.asr is not None else "",
            events=events,
            final_words=final,
            turn_start_s=self._turn_start_s,
            turn_end_s=self._turn_end_s,
        )

    def _track_speech_run(self) -> None:
        if self.turns.state in (VadState.STARTING, VadState.SPEAKING):
            if self._run_start_s is None:
                self._run_start_s = self._chunk_t_s - VAD_CHUNK_S
        else:
            self._run_start_s = None

    def _on_event(self, event: VadEvent) -> None:
        if event.kind == "start":
            self._turn_start_s = event.t_s
            if self.asr is not None:
                begin_s = max(0.0, event.t_s - PREROLL_S, self._t_s - HISTORY_S)
                n_back = int(round((self._t_s - begin_s) * VAD_RATE_HZ))
                self.asr.begin(self._t_s - n_back / VAD_RATE_HZ, self._history[len(self._history) - n_back :])
        elif event.kind == "end":
            self._turn_end_s = event.t_s
            if self.asr is not None:
                self.asr.finish()


class ListeningBackend:
    """The step clock shared by the backends that hear the user through a `UserListener`."""

    listener: UserListener
    _step_index: int
    _last_agent_pcm: "np.ndarray | None"

    def skip(self, n_steps: int) -> None:
        """Live mode dropped n_steps of input: advance the clocks so the transcript's times stay true."""
        self._step_index += n_steps
        self.listener.skip(n_steps * STEP_S)
        self._last_agent_pcm = None
