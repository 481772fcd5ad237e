"""The default agent's quality report: ``ecas evaluate --suite default [--json]``.

It loads the generator exactly as the runtime does (the `gesture:` section of ecas/configs/default.yaml, checked
against the local backend's condition spec) and measures:
- on held-out synthetic sessions (the `test` split of a synthetic directory; by default sessions k = 10, 20,
  ..., 100 of seed 0, 3 minutes each, generated on first use and again whenever the generator changes:
  scripts/train_default.sh holds every 10th session of the same data out of training, so none of them was seen),
  the agent's motion generated step by step from what the local dialogue backend would emit for the session's
  agent speech (speech codes of the agent audio, a text token at each word's first step), against the session's
  ground truth: BeatAlign and L1 divergence (the reference protocol of gesture.eval.metrics, built-in skeleton),
  voice-activity accuracy of the VA head, the ratio of mean joint speed while listening to while speaking, and the
  codecs' MPJPE (all three regions through encode -> decode) on what they model, the sessions' ``gesture_poses`` (the
  motion without the micro-motion that the agent's runtime layer adds, gesture.layers.micro_motion), and on the whole
  motion for comparison. 30 minutes in all: the listening/speaking ratio of a single minute moves by ±40 % with the
  sampling seed alone, more than the goal's tolerance;
- on the real BEAT2 clip spoken by the `playback` backend (its DialogueSteps fed to the generator): BeatAlign
  and L1 divergence next to GT's;
- no collapse: the mean joint speed over a 5-minute generated session (held-out conditions, looped) against its
  first minute's.
Goals (issue 7, held-out synthetic) are checked and reported as met or not, never tuned away.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ecas.core.body import REGIONS
from ecas.core.config import build_dataclass, load_yaml
from ecas.core.paths import CHECKPOINTS_DIR, DEFAULT_CONFIG, data_root, real_clip
from ecas.core.threads import limit_threads
from ecas.core.timing import FRAMES_PER_STEP, MOTION_FPS, SAMPLE_RATE_HZ, STEP_HZ, STEP_SAMPLES
from gesture.body.motion import canonicalize
from gesture.body.regions import features_to_motion, motion_to_features
from gesture.body.skeleton import Skeleton
from gesture.codec.evaluation import reconstruct
from gesture.codec.model import GestureCodec
from gesture.config import GestureConfig
from gesture.data.audio import load_audio
from gesture.data.beat2 import Take, find_takes, read_motion
from gesture.data.chunks import motion_at_fps
from gesture.eval import metrics as M
from gesture.generator import GestureGenerator
from gesture.lm.codecs import load_codecs
from gesture.lm.tokenize import TokenizedTake, agent_audio_path, tokenize_take

SHARED_DATA = data_root()
DEFAULT_LM = CHECKPOINTS_DIR / "gesture_lm"
DEFAULT_CODECS = CHECKPOINTS_DIR / "codecs"
GOALS = {
    "l1div_rel_error_max": 0.25,  # |L1div / L1div_GT - 1|
    "beat_align_abs_error_max": 0.05,  # |BeatAlign - BeatAlign_GT|
    "va_accuracy_min": 0.90,
    "energy_ratio_rel_error_max": 0.30,  # |ratio / ratio_GT - 1|
    "codec_mpjpe_mm_max": 20.0,
    "collapse_rel_change_max": 0.30,  # |mean speed (whole) / mean speed (first minute) - 1|
}


@dataclass(frozen=True)
class SuiteOptions:
    config: Path = DEFAULT_CONFIG
    synthetic_root: Path = Path("runs") / "suite_heldout"  # generated on first use (see ensure_heldout)
    beat2_motion: Path = real_clip().with_suffix(".npz")
    beat2_wav: Path = real_clip().with_suffix(".wav")
    mean_speed: Path = SHARED_DATA / "beat2" / "mean_vel_smplxflame_30.npy"
    heldout_sessions: int = 10
    heldout_seconds: float = 180.0
    collapse_minutes: float = 5.0
    seed: int = 0


@dataclass
class Generated:
    poses: np.ndarray  # (2T, 55, 3)
    trans: np.ndarray  # (2T, 3)
    expressions: np.ndarray  # (2T, 100)
    va_prob: np.ndarray  # (T,)
    step_ms: np.ndarray  # (T,) wall time of each generator step
    tokens: np.ndarray  # (T, L) the sampled gesture tokens of each step, every level

    def clip(self) -> M.MotionClip:
        return M.MotionClip(self.poses, self.trans, self.expressions, MOTION_FPS)


# ---------------------------------------------------------------- loading the default agent


def default_gesture_config(config_path: Path) -> tuple[GestureConfig, object]:
    """The `gesture:` and `dialogue:` sections of the app config, with the local backend's spec filled in."""
    from dialogue.config import DialogueConfig
    from dialogue.text_vocab import LOCAL_SPEC

    tree = load_yaml(config_path)
    gesture = build_dataclass(GestureConfig, tree.get("gesture"), "gesture")
    if gesture.lm_checkpoint is None:
        gesture = dataclasses.replace(gesture, lm_checkpoint=DEFAULT_LM)
    if gesture.codec_checkpoints is None:
        gesture = dataclasses.replace(gesture, codec_checkpoints=DEFAULT_CODECS)
    dialogue = build_dataclass(DialogueConfig, tree.get("dialogue"), "dialogue")
    return dataclasses.replace(gesture, dialogue_spec=LOCAL_SPEC), dialogue


def run_generator(
    generator: GestureGenerator, text: np.ndarray, audio: np.ndarray, pcm_24k: np.ndarray | None = None
) -> Generated:
    """Drive the generator with T steps of conditioning: text (T,), audio codes (Q, T), agent audio (T*1920,)."""
    generator.reset()
    n = len(text)
    poses, trans, expressions, tokens, va, step_ms = [], [], [], [], np.full(n, np.nan), np.zeros(n)
    for t in range(n):
        pcm = None if pcm_24k is None else _step_audio(pcm_24k, t)
        start = time.perf_counter()
        out = generator.step(int(text[t]), audio[:, t], pcm)
        step_ms[t] = (time.perf_counter() - start) * 1e3
        poses.append(out.poses)
        trans.append(out.trans)
        expressions.append(out.expressions)
        tokens.append(out.tokens)
        va[t] = out.va_prob
    return Generated(
        np.concatenate(poses), np.concatenate(trans), np.concatenate(expressions), va, step_ms, np.stack(tokens)
    )


def _step_audio(pcm: np.ndarray, step: int) -> np.ndarray:
    out = np.zeros(STEP_SAMPLES, np.float32)
    piece = pcm[step * STEP_SAMPLES : (step + 1) * STEP_SAMPLES]
    out[: len(piece)] = piece
    return out


# ---------------------------------------------------------------- measures


def frame_speeds(poses: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """(T, 55, 3) axis-angle at 25 fps -> (T,) mean joint speed (m/s) of the 55 FK joints, zero translation."""
    joints = M.joints_zero_translation(poses, skeleton)  # (T, 55, 3)
    return M.joint_speeds(joints, MOTION_FPS).mean(axis=1)


def listening_speaking_ratio(speeds: np.ndarray, step_vad: np.ndarray) -> float:
    """Mean speed over listening frames / over speaking frames (vad per step, 2 frames each)."""
    frame_vad = np.repeat(np.asarray(step_vad) > 0, FRAMES_PER_STEP)[: len(speeds)]
    if frame_vad.all() or not frame_vad.any():
        return float("nan")
    return float(speeds[~frame_vad].mean() / speeds[frame_vad].mean())


@torch.no_grad()
def codec_mpjpe_mm(
    codecs: dict[str, GestureCodec], poses: np.ndarray, trans: np.ndarray, expressions: np.ndarray, skeleton: Skeleton
) -> float:
    """MPJPE (mm, 55 joints, zero translation, 25 fps) of the motion through all three codecs (encode -> decode)."""
    features = motion_to_features(poses, trans, expressions, MOTION_FPS)  # region -> (T, F)
    recon = {r: reconstruct(codecs[r], torch.from_numpy(features[r])).numpy() for r in REGIONS}
    n = len(recon["upper"])
    pred, _, _ = features_to_motion(recon["upper"], recon["lower"], recon["face"])
    return 1000 * M.mpjpe_m(M.joints_zero_translation(pred, skeleton), M.joints_zero_translation(poses[:n], skeleton))


def relative_error(value: float, reference: float) -> float:
    return abs(value / reference - 1.0) if reference else float("inf")


# ---------------------------------------------------------------- the three parts


@dataclass
class HeldoutSession:
    take: Take
    tokens: TokenizedTake  # cut to the evaluated steps
    pcm_24k: np.ndarray
    speech: M.SpeechAudio  # the agent audio at its own rate, cut to the evaluated steps
    poses: np.ndarray  # (2T, 55, 3) canonical GT
    trans: np.ndarray
    expressions: np.ndarray
    gesture_poses: (
        np.ndarray
    )  # (2T, 55, 3) canonical GT without the runtime layer's micro-motion (what the codecs model)


HELDOUT_DATA_SEED = 0  # scripts/train_default.sh's data seed; its test split is held out of training
GENERATOR_STAMP = "generator.stamp"  # in a sessions directory: the generator_fingerprint and the seed that made it


def ensure_heldout(root: Path, n_sessions: int) -> None:
    """Generate held-out sessions 10, 20, ... of the training data's seed into `root` (see ensure_sessions)."""
    from gesture.synth.build import held_out_period
    from gesture.synth.config import SynthConfig

    period = held_out_period(SynthConfig())
    ensure_sessions(root, HELDOUT_DATA_SEED, range(period, period * (n_sessions + 1), period))


def session_stamp(seed: int) -> str:
    """What `ensure_sessions` writes into GENERATOR_STAMP: the current generator's fingerprint and the data seed (the
    take ids do not name the seed)."""
    from gesture.synth.build import generator_fingerprint

    return f"{generator_fingerprint()} seed {seed}"


def has_sessions(root: Path, seed: int, count: int) -> bool:
    """`root` holds at least `count` test takes, made by the current generator from `seed`."""
    stamp = root / GENERATOR_STAMP
    return stamp.is_file() and stamp.read_text().strip() == session_stamp(seed) and len(_test_takes(root)) >= count


def ensure_sessions(root: Path, seed: int, numbers: range) -> None:
    """Generate synthetic sessions `numbers` of `seed` into `root`, all in its test split, unless it already holds
    as many test takes made by the current generator from that seed."""
    from gesture.synth.build import SESSION_MINUTES, generate_sessions
    from gesture.synth.config import SynthConfig

    if has_sessions(root, seed, len(numbers)):
        return
    ids = generate_sessions(SynthConfig(), root, seed, numbers, SESSION_MINUTES, jobs=2)
    (root / "train_test_split.csv").write_text("id,type\n" + "".join(f"{i},test\n" for i in ids))
    (root / GENERATOR_STAMP).write_text(session_stamp(seed) + "\n")


def _session_order(take: Take) -> list:
    """Ids compare by their numeric parts, so session 10 comes before 100."""
    return [int(part) if part.isdigit() else part for part in take.take_id.split("_")]


def _test_takes(root: Path) -> list[Take]:
    return sorted((t for t in find_takes(root) if t.split == "test"), key=_session_order)


def load_heldout(
    root: Path, codecs: dict[str, GestureCodec], n_sessions: int, max_seconds: float
) -> list[HeldoutSession]:
    from dialogue.speech_tokenizer import DEFAULT_CHECKPOINT, SpeechTokenizer

    takes = _test_takes(root)[:n_sessions]
    if not takes:
        raise FileNotFoundError(
            f"{root}: no held-out (test split) synthetic sessions; generate them with ecas synthetic"
        )
    tokenizer = SpeechTokenizer.load(DEFAULT_CHECKPOINT)
    max_steps = int(max_seconds * STEP_HZ)
    sessions = []
    for take in takes:
        tok = tokenize_take(take, codecs, tokenizer)
        n = min(tok.num_steps, max_steps)
        tok = TokenizedTake(tok.gesture_tokens[:, :n], tok.text_tokens[:n], tok.audio_codes[:, :n], tok.vad[:n])
        motion = motion_at_fps(read_motion(take.motion_path), MOTION_FPS)
        poses, trans = canonicalize(motion.poses[: 2 * n], motion.trans[: 2 * n])
        layer = motion_at_fps(read_motion(take.motion_path, gesture_layer=True), MOTION_FPS)
        gesture_poses, _ = canonicalize(layer.poses[: 2 * n], layer.trans[: 2 * n])
        wav = agent_audio_path(take)
        seconds = n / STEP_HZ
        pcm = load_audio(wav, SAMPLE_RATE_HZ)[: int(seconds * SAMPLE_RATE_HZ)]
        native = M.load_speech(wav)
        speech = M.SpeechAudio(native.pcm[: int(seconds * native.sample_rate_hz)], native.sample_rate_hz)
        sessions.append(
            HeldoutSession(take, tok, pcm, speech, poses, trans, motion.expressions[: 2 * n], gesture_poses)
        )
    return sessions


def evaluate_heldout(
    generator: GestureGenerator,
    codecs: dict[str, GestureCodec],
    sessions: list[HeldoutSession],
    mean_speed: np.ndarray,
    skeleton: Skeleton,
) -> dict:
    from gesture.eval.scores import evaluate_motion

    rows = []
    for s in sessions:
        gen = run_generator(generator, s.tokens.text_tokens, s.tokens.audio_codes, s.pcm_24k)
        gt = M.MotionClip(s.poses, s.trans, s.expressions, MOTION_FPS)
        scores = evaluate_motion(gen.clip(), gt, s.speech, mean_speed, skeleton, encoders=())
        vad = s.tokens.vad
        rows.append(
            {
                "session": s.take.take_id,
                "seconds": s.tokens.num_steps / STEP_HZ,
                "beat_align": scores["beat_align"],
                "beat_align_gt": scores["beat_align_gt"],
                "l1div": scores["l1div"],
                "l1div_gt": scores["l1div_gt"],
                "va_accuracy": float(((gen.va_prob > 0.5) == (vad > 0)).mean()),
                "va_gt_active_fraction": float(vad.mean()),
                "energy_ratio": listening_speaking_ratio(frame_speeds(gen.poses, skeleton), vad),
                "energy_ratio_gt": listening_speaking_ratio(frame_speeds(s.poses, skeleton), vad),
                "codec_mpjpe_mm": codec_mpjpe_mm(codecs, s.gesture_poses, s.trans, s.expressions, skeleton),
                "codec_mpjpe_whole_motion_mm": codec_mpjpe_mm(codecs, s.poses, s.trans, s.expressions, skeleton),
                "step_ms_median": float(np.median(gen.step_ms)),
            }
        )
    mean = {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0] if k != "session"}
    return {"sessions": rows, "mean": mean}


def evaluate_beat2_playback(
    generator: GestureGenerator, dialogue_cfg, opts: SuiteOptions, mean_speed: np.ndarray, skeleton: Skeleton
) -> dict:
    """The real clip's speech played by the playback backend (silent user), its steps driving the generator."""
    from dialogue.listener import UserListener
    from dialogue.local_backend import load_speech_tokenizer
    from dialogue.playback_backend import PlaybackBackend, recording_utterance
    from gesture.eval.scores import evaluate_motion

    gt = M.load_motion_clip(opts.beat2_motion).at_fps(MOTION_FPS)
    n_steps = len(gt.poses) // FRAMES_PER_STEP
    backend = PlaybackBackend(
        recording_utterance(str(opts.beat2_wav), None),
        UserListener(dialogue_cfg.vad, dialogue_cfg.echo, None),
        load_speech_tokenizer(dialogue_cfg.speech_tokenizer),
    )
    silence = np.zeros(STEP_SAMPLES, np.float32)
    steps = [backend.step(silence) for _ in range(n_steps)]
    backend.close()
    text = np.array([s.text_token for s in steps])
    audio = np.stack([s.agent_codes for s in steps], axis=1)  # (Q, T)
    pcm = np.concatenate([s.agent_pcm for s in steps])
    gen = run_generator(generator, text, audio, pcm)
    poses, trans = canonicalize(gt.poses[: 2 * n_steps], gt.trans[: 2 * n_steps])
    gt_clip = M.MotionClip(poses, trans, gt.expressions[: 2 * n_steps], MOTION_FPS)
    scores = evaluate_motion(gen.clip(), gt_clip, M.load_speech(opts.beat2_wav), mean_speed, skeleton, encoders=())
    keys = ("beat_align", "beat_align_gt", "l1div", "l1div_gt", "beat_align_corrected", "beat_align_corrected_gt")
    return {
        "clip": opts.beat2_motion.stem,
        "seconds": n_steps / STEP_HZ,
        "text_tokens": int((text >= 0).sum()),
        **{k: scores[k] for k in keys},
    }


def evaluate_collapse(
    generator: GestureGenerator, sessions: list[HeldoutSession], minutes: float, skeleton: Skeleton
) -> dict:
    """Mean joint speed over a long session (held-out conditions looped) against its first minute's."""
    n = int(minutes * 60 * STEP_HZ)
    reps = math.ceil(n / sum(s.tokens.num_steps for s in sessions))
    text = np.tile(np.concatenate([s.tokens.text_tokens for s in sessions]), reps)[:n]
    audio = np.tile(np.concatenate([s.tokens.audio_codes for s in sessions], axis=1), reps)[:, :n]
    pcm = np.tile(np.concatenate([_pad_steps(s.pcm_24k, s.tokens.num_steps) for s in sessions]), reps)
    gen = run_generator(generator, text, audio, pcm[: n * STEP_SAMPLES])
    speeds = frame_speeds(gen.poses, skeleton)
    first = speeds[: int(60 * MOTION_FPS)].mean()
    minute_means = [float(speeds[i : i + 60 * MOTION_FPS].mean()) for i in range(0, len(speeds), 60 * MOTION_FPS)]
    return {
        "minutes": minutes,
        "mean_speed": float(speeds.mean()),
        "first_minute_speed": float(first),
        "per_minute_speed": minute_means,
        "rel_change": float(speeds.mean() / first - 1.0),
        "step_ms_median": float(np.median(gen.step_ms)),
        "step_ms_p95": float(np.percentile(gen.step_ms, 95)),
    }


def _pad_steps(pcm: np.ndarray, n_steps: int) -> np.ndarray:
    out = np.zeros(n_steps * STEP_SAMPLES, np.float32)
    out[: min(len(pcm), len(out))] = pcm[: len(out)]
    return out


# ---------------------------------------------------------------- report


def check_goals(heldout: dict, collapse: dict) -> dict:
    m = heldout["mean"]
    values = {
        "l1div_rel_error": relative_error(m["l1div"], m["l1div_gt"]),
        "beat_align_abs_error": abs(m["beat_align"] - m["beat_align_gt"]),
        "va_accuracy": m["va_accuracy"],
        "energy_ratio_rel_error": relative_error(m["energy_ratio"], m["energy_ratio_gt"]),
        "codec_mpjpe_mm": m["codec_mpjpe_mm"],
        "collapse_rel_change": abs(collapse["rel_change"]),
    }
    met = {
        "l1div_rel_error": values["l1div_rel_error"] <= GOALS["l1div_rel_error_max"],
        "beat_align_abs_error": values["beat_align_abs_error"] <= GOALS["beat_align_abs_error_max"],
        "va_accuracy": values["va_accuracy"] >= GOALS["va_accuracy_min"],
        "energy_ratio_rel_error": values["energy_ratio_rel_error"] <= GOALS["energy_ratio_rel_error_max"],
        "codec_mpjpe_mm": values["codec_mpjpe_mm"] <= GOALS["codec_mpjpe_mm_max"],
        "collapse_rel_change": values["collapse_rel_change"] <= GOALS["collapse_rel_change_max"],
    }
    return {"values": values, "met": met, "limits": GOALS}


def run_suite(opts: SuiteOptions, progress=print) -> dict:
    from gesture.process import build_generator

    torch.set_num_threads(1)
    started = time.perf_counter()
    gesture_cfg, dialogue_cfg = default_gesture_config(opts.config)
    generator = build_generator(gesture_cfg, opts.seed)
    codecs = load_codecs(gesture_cfg.codec_checkpoints)  # offline copies: the generator's decoders are streaming
    skeleton = Skeleton.default()
    mean_speed = M.load_mean_speed(opts.mean_speed)
    ensure_heldout(opts.synthetic_root, opts.heldout_sessions)
    sessions = load_heldout(opts.synthetic_root, codecs, opts.heldout_sessions, opts.heldout_seconds)
    progress(f"held-out synthetic: {len(sessions)} sessions")
    heldout = evaluate_heldout(generator, codecs, sessions, mean_speed, skeleton)
    progress("BEAT2 clip through the playback backend")
    beat2 = evaluate_beat2_playback(generator, dialogue_cfg, opts, mean_speed, skeleton)
    progress(f"no-collapse: {opts.collapse_minutes:g} minutes")
    collapse = evaluate_collapse(generator, sessions, opts.collapse_minutes, skeleton)
    generator.close()
    return {
        "checkpoints": {"lm": str(gesture_cfg.lm_checkpoint), "codecs": str(gesture_cfg.codec_checkpoints)},
        "sampling": {
            "temperature": gesture_cfg.temperature,
            "top_p_temporal": gesture_cfg.top_p_temporal,
            "top_p_depth": gesture_cfg.top_p_depth,
            "cfg_scale": gesture_cfg.cfg_scale,
            "dtype": gesture_cfg.dtype,
            "seed": opts.seed,
        },
        "heldout_synthetic": heldout,
        "beat2_playback": beat2,
        "no_collapse": collapse,
        "goals": check_goals(heldout, collapse),
        "wall_s": time.perf_counter() - started,
    }


def format_table(report: dict) -> str:
    m, b, c, g = (report["heldout_synthetic"]["mean"], report["beat2_playback"], report["no_collapse"], report["goals"])
    ok = {k: ("met" if v else "NOT met") for k, v in g["met"].items()}
    lines = [
        "| measure | generated | ground truth | goal | status |",
        "|---|---|---|---|---|",
        f"| held-out synthetic BeatAlign | {m['beat_align']:.3f} | {m['beat_align_gt']:.3f} | within 0.05 of GT "
        f"| {ok['beat_align_abs_error']} |",
        f"| held-out synthetic L1div | {m['l1div']:.3f} | {m['l1div_gt']:.3f} | within ±25% of GT "
        f"| {ok['l1div_rel_error']} |",
        f"| voice-activity accuracy | {m['va_accuracy']:.3f} | – | ≥ 0.90 | {ok['va_accuracy']} |",
        f"| listening/speaking motion energy | {m['energy_ratio']:.3f} | {m['energy_ratio_gt']:.3f} "
        f"| within ±30% of GT | {ok['energy_ratio_rel_error']} |",
        f"| codec MPJPE (mm, 3 regions; gesture layer) | {m['codec_mpjpe_mm']:.1f} | – | ≤ 20 "
        f"| {ok['codec_mpjpe_mm']} |",
        f"| codec MPJPE (mm, 3 regions; with the micro-motion) | {m['codec_mpjpe_whole_motion_mm']:.1f} | – | – | – |",
        f"| BEAT2 clip (playback) BeatAlign | {b['beat_align']:.3f} | {b['beat_align_gt']:.3f} | – | – |",
        f"| BEAT2 clip (playback) L1div | {b['l1div']:.3f} | {b['l1div_gt']:.3f} | – | – |",
        f"| no collapse: mean speed {c['minutes']:g} min / first min "
        f"| {c['mean_speed']:.3f} / {c['first_minute_speed']:.3f} m/s "
        f"| – | within ±30% | {ok['collapse_rel_change']} |",
    ]
    return "\n".join(lines)


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def main(argv: Sequence[str] | None = None) -> int:
    limit_threads()
    defaults = SuiteOptions()
    parser = argparse.ArgumentParser(prog="ecas suite", description="Quality report of the shipped default agent.")
    parser.add_argument("--suite", choices=["default"], default="default")
    parser.add_argument("--json", action="store_true", help="print one JSON object after the table")
    parser.add_argument("--config", type=Path, default=defaults.config, help="app config with the gesture: section")
    parser.add_argument(
        "--synthetic",
        type=Path,
        default=defaults.synthetic_root,
        help="synthetic directory whose test split is held out",
    )
    parser.add_argument("--sessions", type=int, default=defaults.heldout_sessions)
    parser.add_argument("--seconds", type=float, default=defaults.heldout_seconds, help="per held-out session")
    parser.add_argument("--collapse-minutes", type=float, default=defaults.collapse_minutes)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--out", type=Path, help="also write the JSON report here")
    args = parser.parse_args(argv)
    opts = dataclasses.replace(
        defaults,
        config=args.config,
        synthetic_root=args.synthetic,
        heldout_sessions=args.sessions,
        heldout_seconds=args.seconds,
        collapse_minutes=args.collapse_minutes,
        seed=args.seed,
    )
    try:
        report = _json_safe(run_suite(opts, progress=lambda msg: print(msg, file=sys.stderr)))
    except (FileNotFoundError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(format_table(report), file=sys.stderr if args.json else sys.stdout)
    if args.json:
        print(json.dumps(report))
    if args.out:
        args.out.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
