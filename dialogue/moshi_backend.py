"""Kyutai's Moshi through the `moshi` package, from local files only.

Each step: Mimi encodes the user's 1920 samples to 8 codes, `LMGen.step` returns (after its
max-delay warm-up) Moshi's text token and its own 8 audio codes, and Mimi decodes those to the agent's
PCM. The user side also runs the shared listener (VAD, optional ASR) for the transcript.
"""

import contextlib
import json
from pathlib import Path

import numpy as np
import torch

from dialogue.config import DialogueConfig, MoshiConfig
from dialogue.listener import ListeningBackend, UserListener
from dialogue.local_backend import check_user_pcm, user_turn_from
from dialogue.transcript import Transcript, Turn, Word
from ecas.core.messages import DialogueStep
from ecas.core.spec import ConditionSpec
from ecas.core.timing import STEP_S

N_CODES = 8
EXPECTED_FILES = {
    "lm_weights": "model.safetensors",
    "mimi_weights": "tokenizer-e351c8d8-checkpoint125.safetensors",
    "tokenizer": "tokenizer_spm_32k_3.model",
}
TEXT_SKIP_IDS = (0, 3)  # Moshi's end-of-padding and padding text tokens carry no word
SPEAKING_RMS = 0.01
AGENT_TURN_GAP_S = 1.2  # silence in Moshi's text stream that closes an agent turn


class MoshiWeightsError(FileNotFoundError):
    pass


def check_moshi_files(cfg: MoshiConfig) -> dict[str, Path]:
    """The three local files, or one error naming every missing one and what it is expected to be."""
    paths, missing = {}, []
    for key, expected in EXPECTED_FILES.items():
        value = getattr(cfg, key)
        if value is None or not Path(value).is_file():
            missing.append(f"dialogue.moshi.{key} = {value!r} (expected a local file like {expected!r})")
        else:
            paths[key] = Path(value)
    if missing:
        raise MoshiWeightsError(
            "the moshi backend needs Moshi's weights as local files (nothing is downloaded at run time); missing: "
            + "; ".join(missing)
            + ". Get them from the kyutai/moshiko-pytorch-bf16 release and set these options."
        )
    return paths


def moshi_spec(lm) -> ConditionSpec:
    """The conditioning vocabulary of a Moshi LM: equals MOSHI_SPEC for the released 7B."""
    return ConditionSpec(name="moshi", text_vocab=lm.text_card + 1, audio_card=lm.card + 1, embed_dim=lm.dim)


def _read_json(path: str | None) -> dict | None:
    return None if path is None else json.loads(Path(path).read_text())


class MoshiBackend(ListeningBackend):
    def __init__(
        self,
        mimi,
        lm,
        text_tokenizer,
        listener: UserListener,
        temp: float,
        temp_text: float,
        top_k: int,
        top_k_text: int,
        cfg_coef: float,
        device: str = "cpu",
    ):
        from moshi.models import LMGen

        self.device = torch.device(device)
        self.mimi, self.lm, self.text_tokenizer, self.listener = mimi, lm, text_tokenizer, listener
        self.spec = moshi_spec(lm)
        no_text_cfg = cfg_coef != 1.0 and lm.fuser is None
        self.lm_gen = LMGen(
            lm,
            temp=temp,
            temp_text=temp_text,
            top_k=top_k,
            top_k_text=top_k_text,
            cfg_coef=cfg_coef,
            cfg_is_no_text=no_text_cfg,
        )
        self.mimi.streaming_forever(1)
        self.lm_gen.streaming_forever(1)
        self.transcript = Transcript("moshi")
        self.reset()
        self.step(np.zeros(self.mimi.frame_size, np.float32))  # warm-up (and torch.compile on GPU) before ready
        self.reset()

    def _compile_context(self):
        """torch.compile on CPU costs ~10 s at the first step and needs a C compiler: only use it on GPU."""
        from moshi.utils.compile import no_compile

        return contextlib.nullcontext() if self.device.type == "cuda" else no_compile()

    @classmethod
    def from_config(cls, cfg: DialogueConfig, seed: int = 0) -> "MoshiBackend":
        import sentencepiece
        from moshi.models import loaders

        m = cfg.moshi
        files = check_moshi_files(m)
        torch.manual_seed(seed)
        lm_kwargs = _read_json(m.lm_config)
        n_codebooks = N_CODES if lm_kwargs is None else max(lm_kwargs["dep_q"], lm_kwargs["n_q"] - lm_kwargs["dep_q"])
        dtype = torch.bfloat16 if m.device.startswith("cuda") else torch.float32
        mimi = loaders.get_mimi(
            files["mimi_weights"], _read_json(m.mimi_config), device=m.device, num_codebooks=n_codebooks
        )
        lm = loaders.get_moshi_lm(files["lm_weights"], lm_kwargs, device=m.device, dtype=dtype)
        tokenizer = sentencepiece.SentencePieceProcessor(str(files["tokenizer"]))
        return cls(
            mimi,
            lm,
            tokenizer,
            UserListener(cfg.vad, cfg.echo, cfg.asr),
            m.temp,
            m.temp_text,
            m.top_k,
            m.top_k_text,
            m.cfg_coef,
            m.device,
        )

    def reset(self) -> None:
        self.mimi.reset_streaming()
        self.lm_gen.reset_streaming()
        self.listener.reset()
        self.transcript.turns.clear()
        self._step_index = 0
        self._agent_turn: Turn | None = None
        self._last_text_s = 0.0
        self._last_agent_pcm: np.ndarray | None = None

    def close(self) -> None:
        pass

    @torch.no_grad()
    def step(self, user_pcm: np.ndarray) -> DialogueStep:
        user_pcm = check_user_pcm(user_pcm)
        t_s = self._step_index * STEP_S
        heard = self.listener.step(user_pcm, self._last_agent_pcm)
        if heard.final_words is not None:
            user_turn_from(heard, self.transcript).answered = None
        x = torch.from_numpy(user_pcm).to(self.device)[None, None]  # (1, 1, 1920)
        agent_pcm = np.zeros_like(user_pcm)
        agent_codes = np.full(N_CODES, -1, np.int32)
        text_token, piece = -1, ""
        with self._compile_context():
            user_codes = self.mimi.encode(x)  # (1, 8, 1)
            out = self.lm_gen.step(user_codes)  # None during LMGen's delay warm-up, else (1, 1 + 8, 1)
            if out is not None:
                codes = out[:, 1 : 1 + N_CODES]  # (1, 8, 1)
                agent_pcm = self.mimi.decode(codes)[0, 0].float().cpu().numpy().astype(np.float32)  # (1920,)
        if out is not None:
            text_token = int(out[0, 0, 0])
            agent_codes = codes[0, :, 0].cpu().numpy().astype(np.int32)
            piece = self._text_piece(text_token, t_s)
        self._last_agent_pcm = agent_pcm
        self._step_index += 1
        return DialogueStep(
            agent_pcm=agent_pcm,
            user_pcm=user_pcm,
            agent_codes=agent_codes,
            user_codes=user_codes[0, :, 0].cpu().numpy().astype(np.int32),
            text_token=text_token,
            text_piece=piece,
            user_vad_prob=heard.vad_prob,
            user_vad_state=heard.vad_state,
            agent_speaking=bool(np.sqrt(np.mean(agent_pcm**2)) > SPEAKING_RMS),
            user_partial=heard.partial,
            user_words=" ".join(w.word for w in heard.final_words or []),
            agent_interrupted=False,
        )

    def _text_piece(self, token: int, t_s: float) -> str:
        """The word piece of a text token (sentencepiece '▁' marks a word start); extends the agent transcript."""
        if token in TEXT_SKIP_IDS or token >= self.text_tokenizer.get_piece_size():
            return ""
        piece = self.text_tokenizer.id_to_piece(token)
        if self._agent_turn is None or t_s - self._last_text_s > AGENT_TURN_GAP_S:
            self._agent_turn = self.transcript.add(Turn("agent", t_s, t_s))
        turn = self._agent_turn
        if piece.startswith("▁") or not turn.words:
            if turn.words:
                turn.words[-1].end_s = t_s
            turn.words.append(Word(piece.lstrip("▁"), t_s, t_s + STEP_S))
        else:
            turn.words[-1].word += piece
            turn.words[-1].end_s = t_s + STEP_S
        turn.end_s = t_s + STEP_S
        turn.text = " ".join(w.word for w in turn.words)
        self._last_text_s = t_s
        return piece.replace("▁", " ")
