"""The default backend, CPU and offline: VAD + pocketsphinx -> responder -> espeak-ng, with speech codes.

Turn taking: at each pause of the user the end-of-turn model judges whether the turn is complete (`turn.detector`
smart_turn, docs/turn_taking.md; with `silence`, the turn ends after `vad.stop_s`); while the user pauses mid-turn
nothing is sent to the responder. Once a finished turn's words are recognised the
responder's sentences are spoken. User speech over the agent for `barge_in_s` cuts the agent at once and
that user turn is answered; shorter overlaps (backchannels) are transcribed but not answered.
"""

import time
from pathlib import Path

import numpy as np

from dialogue.config import DialogueConfig
from dialogue.listener import Heard, ListeningBackend, UserListener
from dialogue.responder import Reply, Responder, build_responder
from dialogue.speaker import Speaker, SpokenStep
from dialogue.speech_tokenizer import DEFAULT_CHECKPOINT, SpeechTokenizer, StreamingSpeechEncoder
from dialogue.text_vocab import LOCAL_SPEC
from dialogue.transcript import Transcript, Turn, Word
from dialogue.tts import EspeakTts
from ecas.core.messages import DialogueStep, VadState
from ecas.core.timing import STEP_S, STEP_SAMPLES


def check_user_pcm(user_pcm: np.ndarray) -> np.ndarray:
    """A step of user audio as finite float32 (1920,); NaN/inf become 0, a wrong shape is an error."""
    pcm = np.asarray(user_pcm, np.float32)
    if pcm.shape != (STEP_SAMPLES,):
        raise ValueError(f"user audio step must have shape ({STEP_SAMPLES},), got {pcm.shape}")
    return np.nan_to_num(pcm, nan=0.0, posinf=1.0, neginf=-1.0)


def step_message(
    user_pcm: np.ndarray,
    heard: Heard,
    spoken: SpokenStep,
    agent_codes: StreamingSpeechEncoder,
    user_codes: StreamingSpeechEncoder,
    user_words: str,
) -> DialogueStep:
    """The step's message: both voices, their speech codes, the agent's text token, what was heard."""
    return DialogueStep(
        agent_pcm=spoken.pcm,
        user_pcm=user_pcm,
        agent_codes=agent_codes.step(spoken.pcm),
        user_codes=user_codes.step(user_pcm),
        text_token=spoken.text_token,
        text_piece=spoken.text_piece,
        user_vad_prob=heard.vad_prob,
        user_vad_state=heard.vad_state,
        agent_speaking=spoken.speaking,
        user_partial=heard.partial,
        user_words=user_words,
        agent_interrupted=spoken.interrupted,
    )


def load_speech_tokenizer(path: str | None) -> SpeechTokenizer:
    return SpeechTokenizer.load(Path(path) if path else DEFAULT_CHECKPOINT)


def user_turn_from(heard: Heard, transcript: Transcript) -> Turn:
    words = [Word(w.word, w.start_s, w.end_s) for w in heard.final_words]
    start = min([heard.turn_start_s] + [w.start_s for w in words])
    end = max([heard.turn_end_s] + [w.end_s for w in words])
    return transcript.add(Turn("user", start, end, words, text=" ".join(w.word for w in words)))


class LocalBackend(ListeningBackend):
    spec = LOCAL_SPEC

    def __init__(
        self,
        listener: UserListener,
        tts: EspeakTts,
        responder: Responder,
        tokenizer: SpeechTokenizer,
        barge_in_s: float,
    ):
        self.transcript = Transcript("local")
        self.listener = listener
        self.speaker = Speaker(self.transcript, tts.synthesize)
        self.responder = responder
        self.agent_codes = StreamingSpeechEncoder(tokenizer)
        self.user_codes = StreamingSpeechEncoder(tokenizer)
        self.barge_in_s = barge_in_s
        self.reset()

    @classmethod
    def from_config(cls, cfg: DialogueConfig, seed: int = 0) -> "LocalBackend":
        r = cfg.responder
        responder = build_responder(
            r.kind,
            seed,
            url=r.url,
            model=r.model,
            timeout_s=r.timeout_s,
            max_tokens=r.max_tokens,
            system_prompt=r.system_prompt,
            fallback_text=r.fallback_text,
            api_key_env=r.api_key_env,
        )
        tts = EspeakTts(cfg.tts.voice, cfg.tts.rate_wpm, cfg.tts.pitch)
        tts.synthesize("Hello.")  # loads the voice now, and fails early on a bad one
        backend = cls(
            UserListener(cfg.vad, cfg.echo, cfg.asr, cfg.turn),
            tts,
            responder,
            load_speech_tokenizer(cfg.speech_tokenizer),
            cfg.barge_in_s,
        )
        backend.warm_up()
        return backend

    def warm_up(self) -> None:
        """One silent step (first ONNX / torch / decoder calls are slow), then a clean state."""
        self.step(np.zeros(STEP_SAMPLES, np.float32))
        self.reset()

    def reset(self) -> None:
        self.listener.reset()
        self.speaker.reset()
        self.agent_codes.reset()
        self.user_codes.reset()
        self.transcript.turns.clear()
        self._step_index = 0
        self._last_agent_pcm: np.ndarray | None = None
        self._reply: Reply | None = None
        self._barged_in = False  # the current user turn cut the agent: answer it
        self._awaiting_answer_since_s: float | None = None  # end of the user speech being answered
        self.response_latencies_s: list[float] = []  # end of user speech -> first agent audio can play

    def close(self) -> None:
        if self._reply is not None:
            self._reply.cancel()

    def step(self, user_pcm: np.ndarray) -> DialogueStep:
        t_cpu = time.process_time()
        user_pcm = check_user_pcm(user_pcm)
        t_s = self._step_index * STEP_S
        heard = self.listener.step(user_pcm, self._last_agent_pcm)
        user_words = self._take_user_turn(heard)
        self._pull_reply()
        spoken = self._barge_in(t_s) if self._user_takes_the_turn(heard) else self.speaker.step(t_s)
        if spoken.first_audio and self._awaiting_answer_since_s is not None:
            ready_s = (self._step_index + 1) * STEP_S + (time.process_time() - t_cpu)
            self.response_latencies_s.append(ready_s - self._awaiting_answer_since_s)
            self._awaiting_answer_since_s = None
        self._last_agent_pcm = spoken.pcm
        self._step_index += 1
        return step_message(user_pcm, heard, spoken, self.agent_codes, self.user_codes, user_words)

    def _take_user_turn(self, heard: Heard) -> str:
        """Record a finished user turn; answer it unless it was a short overlap with the agent talking."""
        if heard.final_words is None:
            return ""
        turn = user_turn_from(heard, self.transcript)
        answer = bool(turn.words) and (self._barged_in or not self.speaker.busy)
        turn.answered = answer
        self._barged_in = False
        if answer:
            self._reply = self.responder.start(turn.text)
            self.speaker.begin_reply()
            self._awaiting_answer_since_s = heard.turn_end_s
        return turn.text

    def _pull_reply(self) -> None:
        if self._reply is None:
            return
        for sentence in self._reply.poll():
            self.speaker.say(sentence)
        if self._reply.done:
            self.speaker.end_reply()
            self._reply = None

    def _user_takes_the_turn(self, heard: Heard) -> bool:
        """User speech for barge_in_s while a reply is playing or pending."""
        return (
            self.speaker.busy
            and heard.vad_state in (VadState.STARTING, VadState.SPEAKING)
            and heard.speech_run_s >= self.barge_in_s
        )

    def _barge_in(self, t_s: float) -> SpokenStep:
        """Stop the agent at this step, drop its reply, and answer the user's turn when it ends."""
        if self._reply is not None:
            self._reply.cancel()
            self._reply = None
        self._barged_in = True
        self._awaiting_answer_since_s = None
        return self.speaker.cut(t_s)
