"""The synthetic agent's whole-body motion for one conversation, at 25 fps.

Composition (all local rotations are offsets applied on top of the BEAT2-calibrated rest posture):
posture (stance, weight shifts, sway, breathing) -> torso FK -> arm IK to the planned wrist targets
(gestures.py) with palm twist and wrist flexion -> leg IK to the planted feet -> fingers (hands.py) ->
head (speaking nods on stressed words, per-sentence tilts/turns, listening nods at the user's pauses)
-> face (jaw from the agent's speech envelope, blinks, brows, smiles, mouth shapes; face.py) -> micro-motion:
low-passed rotation noise on the torso, neck, head and arm joints (real speakers are never still), slow and quick,
its sizes and bandwidth per joint fitted to the real clip (calibration.json ``micro_motion``), louder with the agent's
own speech and calmer while it listens -> posture reflexes: the spine and neck counter quick turns beneath them
(reflex.py). The collars, elbows and wrists end within soft range-of-motion limits
(``JOINT_SOFT_LIMITS_RAD``, at the real clip's tail).
The agent's own voice activity (``vad``) and the user's (``user_vad``) come out as per-frame labels, and
``gesture_poses``: the poses without the micro-motion of ``LAYERED_MICRO_JOINTS``, which the agent adds at run time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import gaussian_filter1d, minimum_filter1d

from ecas.core.body import COLLARS, ELBOWS, NECK_HEAD, NUM_JOINTS, PELVIS, SHOULDERS, SPINE, WRISTS
from gesture.body.rotation import axis_angle_to_matrix, matrix_to_axis_angle, rotation_about_y
from gesture.body.skeleton import Skeleton, forward_kinematics
from gesture.layers.reflex import PostureReflexes
from gesture.layers.signal import log_normal_gate
from gesture.synth.calibration import MICRO_FAST_HZ, MicroNoise, load_calibration
from gesture.synth.config import LAYERED_MICRO_JOINTS, SynthConfig
from gesture.synth.conversation import AGENT, MIN_PAUSE_S, USER, Conversation, activity_frames
from gesture.synth.face import JAW_OPEN_RAD, blink_track, expressions_from_activations
from gesture.synth.gestures import ArmTracks, plan_arms
from gesture.synth.hands import blend_hands
from gesture.synth.ik import TwoBoneChain
from gesture.synth.posture import Posture, highest_pelvis, plan_posture
from gesture.synth.tracks import KeyTrack, add_bump, lowpass_noise, smooth_noise

LISTENING_ENERGY = 0.55  # relative liveliness while listening (1 while speaking)
MICRO_LISTENING = 0.45  # micro-motion while listening, relative to speaking
MICRO_ENVELOPE_GAIN = 0.5  # micro-motion scale 1 - gain/2 .. 1 + gain/2 with the (smoothed) speech envelope
MICRO_ENVELOPE_SMOOTH_S = 0.3
MICRO_GATE_LOG_STD = 0.7  # micro-motion comes and goes: its size is log-normal in time, per body part ...
MICRO_GATE_HZ = 0.4  # ... changing at about this rate (holds of a second or two, bursts between them) ...
MICRO_GATE_MAX = 1.5  # ... and capped (the real clip's fastest joint turns 0.40 rad per frame at 25 fps)
# The elbows and the wrists each have their own, burstier gate (the std of its log), scaled to the same RMS so the
# fitted sizes keep their meaning: a real speaker's forearms and hands hold still between bursts more often than his
# other joints do, and with the arms' gate they held still too rarely (docs/quality_history.md, "Synthetic agent").
ELBOW_GATE_LOG_STD = 1.05
WRIST_GATE_LOG_STD = 0.85
OWN_GATES = ((ELBOWS, ELBOW_GATE_LOG_STD), (WRISTS, WRIST_GATE_LOG_STD))  # joints with their own gates
MIN_FOREARM_FORWARD = 0.1  # forward component of the forearm's direction (the real clip: >= 0.14 in 99% of frames)
ELBOW_SIDES = {
    ELBOWS[0]: 1.0,
    ELBOWS[1]: -1.0,
}  # elbow joint -> the sign of its forearm's rest direction (+x left, -x right)
MICRO_PARTS = (  # pelvis, torso + head; left arm; right arm
    (PELVIS, *SPINE, *NECK_HEAD),
    *((COLLARS[side], SHOULDERS[side], ELBOWS[side], WRISTS[side]) for side in (0, 1)),
)
ROOT_MICRO_MAX_RAD = 0.45  # the pelvis's micro-motion turns it at most about this far (soft limit, tanh): over planted
# feet a larger turn is a step, not a sway (the fitted noise's tail otherwise reaches ~1 rad)
NECK_SHARE = 0.4  # of the head offset on the neck joint; the rest on the head joint
ARM_MIN_FLEX_RAD = 0.2  # the elbows never lock straight (real: the forearm points >= 0.135 forwards in 99 % of frames)
# Wrist targets near or past the arm's full length are eased to at most this share of it (knee, cap; see
# gesture.synth.ik): a target at full reach snaps the arm straight, a jerk of the elbow and then the shoulder.
ARM_SOFT_REACH = (0.93, 0.99)
ARM_MAX_FLEX_STEP_RAD = 0.25  # per frame (real: the fastest joint turns 0.40 rad per frame), see gesture.synth.ik
# The arm joints' range of motion (rad, the local rotation's angle): the calibrated micro-motion (std up to 0.59 rad per
# axis on the elbows and wrists, gated up to 1.5x) on top of a flexed elbow or a bent wrist otherwise reaches ~3 rad.
# Soft limits (identity below the knee, tanh above it, never past the cap) at the real clip's tail: its collars reach
# 0.60/0.68 (p99 0.52/0.57), elbows 1.91/2.45 (p99 1.86/2.37), wrists 1.22/1.30 (p99 1.11/1.17).
JOINT_SOFT_LIMITS_RAD = {
    **{j: (0.55, 0.68) for j in COLLARS},
    **{j: (2.2, 2.55) for j in ELBOWS},
    **{j: (1.1, 1.4) for j in WRISTS},
}  # joint -> (knee, cap)
# The collars take part of each upper arm's swing (as a real shoulder girdle does): the collar turns by this share of
# the upper arm's rotation (chest frame) away from its median direction, smoothed over COLLAR_SMOOTH_S. The arm IK
# then re-solves, so the hands' targets stay and the shoulder joints turn less (without it the shoulders spread far
# wider than a real speaker's and the collars hardly move).
COLLAR_SHARE = 0.5
COLLAR_SMOOTH_S = 0.2
POLE_OUT, POLE_DOWN = (
    0.15,
    -0.8,
)  # where the elbows point (chest frame, per unit backwards): out, down (real arms stay close)
SIDE_JOINTS = {  # (collar, shoulder, elbow, wrist, hip, knee, ankle, foot) per side
    "left": (13, 16, 18, 20, 1, 4, 7, 10),
    "right": (14, 17, 19, 21, 2, 5, 8, 11),
}


@dataclass(frozen=True)
class AgentMotion:
    poses: np.ndarray  # (T, 55, 3) float32 axis-angle
    trans: np.ndarray  # (T, 3) float32
    expressions: np.ndarray  # (T, 100) float32
    vad: np.ndarray  # (T,) uint8 agent voice activity
    user_vad: np.ndarray  # (T,) uint8
    planted: np.ndarray  # (T, 2) planned foot contacts (left, right)
    gesture_poses: np.ndarray  # (T, 55, 3) the poses without the micro-motion of LAYERED_MICRO_JOINTS


def speech_envelope(pcm: np.ndarray, sample_rate_hz: int, n_frames: int, fps: float) -> np.ndarray:
    """(T,) RMS per motion frame normalised by its 95th percentile over voiced frames, in [0, 1]."""
    hop = int(round(sample_rate_hz / fps))
    padded = np.zeros(n_frames * hop, np.float64)
    padded[: min(len(pcm), len(padded))] = pcm[: len(padded)]
    rms = np.sqrt((padded.reshape(n_frames, hop) ** 2).mean(1))
    voiced = rms[rms > 1e-3]
    scale = np.percentile(voiced, 95) if len(voiced) else 1.0
    return np.clip(gaussian_filter1d(rms / scale, 0.7), 0.0, 1.0)


def speaking_frames(conv: Conversation, n_frames: int, fps: float) -> np.ndarray:
    """(T,) 1 inside the agent's turns (not its backchannels)."""
    out = np.zeros(n_frames)
    for turn in conv.turns_of(AGENT, "turn"):
        out[int(turn.start_s * fps) : int(turn.end_s * fps) + 1] = 1.0
    return out


def user_pauses(conv: Conversation) -> list[float]:
    """Times where the user pauses: after a word followed by a gap >= MIN_PAUSE_S, and at turn ends."""
    words = conv.words_of(USER)
    return [a.end_s for a, b in zip(words, words[1:]) if b.start_s - a.end_s >= MIN_PAUSE_S] + (
        [words[-1].end_s] if words else []
    )


def plan_head(
    rng: np.random.Generator,
    conv: Conversation,
    n: int,
    fps: float,
    energy: np.ndarray,
    env: np.ndarray,
    speaking: np.ndarray,
) -> tuple[np.ndarray, list[float]]:
    """(T, 3) head offset (pitch down +x, yaw +y, roll +z) and the times of listening nods."""
    times = np.arange(n) / fps
    pose = KeyTrack(np.zeros(3), max_rate=0.4)
    for turn in conv.turns:
        if turn.kind != "turn":
            continue
        for a, _ in turn.sentence_spans_s if turn.speaker == AGENT else [(turn.start_s, None)]:
            pose.hold(a - 0.3)
            target = (rng.uniform(-0.04, 0.04), rng.uniform(-0.12, 0.12), rng.uniform(-0.07, 0.07))
            if turn.speaker == USER:  # attentive: slightly down, tilted
                target = (rng.uniform(0.0, 0.06), rng.uniform(-0.05, 0.05), rng.uniform(-0.1, 0.1))
            pose.key(a + rng.uniform(0.2, 0.6), target)
    head = pose.evaluate(times)
    for w in conv.words_of(AGENT):
        if w.stressed and rng.random() < 0.3:
            add_bump(head[:, 0], fps, w.peak_s, 0.12, 0.0, 0.22, rng.uniform(0.035, 0.08))
    nods = []
    pauses = user_pauses(conv) + [t.start_s for t in conv.turns_of(AGENT, "backchannel")]
    for t in sorted(pauses):
        idx = min(int(t * fps), n - 1)
        if speaking[idx] > 0 or rng.random() > 0.6:
            continue
        start, period = t + rng.uniform(0.05, 0.3), rng.uniform(0.38, 0.5)
        amp = rng.uniform(0.06, 0.14)
        for k in range(int(rng.integers(1, 4))):
            add_bump(head[:, 0], fps, start + k * period, period * 0.4, 0.0, period * 0.6, amp * 0.7**k)
        nods.append(start)
    head += 0.025 * smooth_noise(rng, n, fps, 0.5, 3) * energy[:, None]
    head[:, 0] -= 0.03 * env
    return head, nods


SMILE_MOOD_HZ = 0.08  # the resting smile drifts slowly (a mood over ~10 s) ...
SMILE_MOOD_RANGE = (0.0, 0.7)  # ... within this range of activation
BROW_STRESS_PROB = 0.4  # a stressed word of the agent raises the brows with this probability
BROW_AMOUNT = (0.5, 1.0)
SMILE_AMOUNT = (0.5, 1.0)


def plan_face(
    rng: np.random.Generator, conv: Conversation, n: int, fps: float, env: np.ndarray, nods: list[float]
) -> np.ndarray:
    """(T, 100) expression coefficients.

    Smiles and brow raises are frequent, large and held for a while: a face codec trained on this keeps them only
    when they carry enough of the expressions' energy (a unit blink moves psi 13x as much as a unit smile)."""
    low, high = SMILE_MOOD_RANGE
    mood = low + (high - low) / (1 + np.exp(-1.5 * smooth_noise(rng, n, fps, SMILE_MOOD_HZ)[:, 0]))
    smile = mood.copy()
    brow, wide, pucker = np.zeros(n), np.zeros(n), np.zeros(n)
    for t in nods:
        if rng.random() < 0.6:
            add_bump(smile, fps, t + 0.2, 0.3, rng.uniform(0.5, 1.8), 0.6, rng.uniform(*SMILE_AMOUNT))
    for w in conv.words_of(AGENT):
        add_bump(wide, fps, w.peak_s, 0.06, 0.0, max(w.end_s - w.peak_s, 0.06), rng.uniform(-0.2, 0.5))
        add_bump(pucker, fps, w.peak_s, 0.06, 0.0, max(w.end_s - w.peak_s, 0.06), rng.uniform(-0.2, 0.4))
        if w.stressed and rng.random() < BROW_STRESS_PROB:
            add_bump(brow, fps, w.peak_s, 0.12, rng.uniform(0.15, 0.5), 0.35, rng.uniform(*BROW_AMOUNT))
        if w.word.endswith("?"):
            add_bump(brow, fps, w.start_s, 0.15, 0.3, 0.4, rng.uniform(*BROW_AMOUNT))
    for turn in conv.turns_of(AGENT, "turn"):
        for _, b in turn.sentence_spans_s:
            if rng.random() < 0.4:
                add_bump(smile, fps, b, 0.3, rng.uniform(0.5, 1.5), 0.6, rng.uniform(*SMILE_AMOUNT))
    for t in user_pauses(conv):
        if rng.random() < 0.25:
            add_bump(brow, fps, t + 0.1, 0.15, 0.3, 0.4, rng.uniform(0.3, 0.7))
    extra_blinks = [t.start_s for t in conv.turns_of(AGENT, "turn") if rng.random() < 0.5]
    return expressions_from_activations(
        {
            "smile": np.clip(smile, 0.0, 1.0),
            "brow_raise": np.clip(brow, 0.0, 1.0),
            "lips_apart": 0.35 * env,
            "mouth_wide": wide * env,
            "pucker": pucker * env,
            "blink": blink_track(rng, n, fps, extra_blinks),
        }
    )


def micro_gate(noise: np.ndarray, log_std: float = MICRO_GATE_LOG_STD) -> np.ndarray:
    """Smooth unit-variance noise -> the gate: log-normal, capped, and scaled to the RMS of the gate of
    ``MICRO_GATE_LOG_STD`` (so the fitted stds of calibration.json keep their size under a burstier gate)."""
    return log_normal_gate(noise, log_std, MICRO_GATE_MAX, MICRO_GATE_LOG_STD)


def micro_motion_scale(speaking: np.ndarray, env: np.ndarray, fps: float) -> np.ndarray:
    """(T,) the micro-motion's scale: calmer while listening, livelier with the agent's own speech energy."""
    turn = MICRO_LISTENING + (1 - MICRO_LISTENING) * gaussian_filter1d(speaking, 8)
    voice = 1 + MICRO_ENVELOPE_GAIN * (gaussian_filter1d(env, MICRO_ENVELOPE_SMOOTH_S * fps) - 0.5)
    return turn * voice


def forearm_forward_scale(planned: np.ndarray, offset: np.ndarray, sign: float) -> np.ndarray:
    """(T,) the share of an elbow's micro-motion ``offset`` (T, 3) that keeps its forearm pointing forwards
    (``MIN_FOREARM_FORWARD``; the elbow never hyperextends), smoothed so that it never jumps."""
    shares = np.linspace(1.0, 0.0, 11)
    forward = np.stack([(planned @ _aa(k * offset))[:, 2, 0] * sign for k in shares], 1)  # (T, 11)
    ok = forward >= MIN_FOREARM_FORWARD
    share = np.where(ok.any(1), shares[np.argmax(ok, axis=1)], 0.0)
    return gaussian_filter1d(minimum_filter1d(share, 9), 1.5)


def micro_noise(rng: np.random.Generator, n: int, fps: float, noise: MicroNoise) -> np.ndarray:
    """(T, 3) one joint's micro-motion noise before its gate (calibration.MicroNoise)."""
    slow = lowpass_noise(rng, n, fps, noise.cutoff_hz, 3)
    fast = lowpass_noise(rng, n, fps, MICRO_FAST_HZ, 3)
    return (slow + noise.fast_ratio * fast) * noise.std_rad[None]


def micro_motion(
    rng: np.random.Generator, n: int, fps: float, params: dict[int, MicroNoise], scale: np.ndarray
) -> dict[int, np.ndarray]:
    """Per joint, (T, 3) local rotation offsets: its ``micro_noise`` times ``scale`` (T,) and its body part's gate,
    or its own (``OWN_GATES``)."""
    part_gates = micro_gate(smooth_noise(rng, n, fps, MICRO_GATE_HZ, len(MICRO_PARTS)))  # (T, parts)
    part_of = {j: k for k, part in enumerate(MICRO_PARTS) for j in part}
    noise = {j: micro_noise(rng, n, fps, params[j]) for j in sorted(params)}  # (T, 3) each
    gates = {j: part_gates[:, part_of.get(j, 0)] for j in noise}
    for joints, log_std in OWN_GATES:  # drawn last, in order: a gate added at the end leaves every earlier draw alone
        own = micro_gate(smooth_noise(rng, n, fps, MICRO_GATE_HZ, len(joints)), log_std)  # (T, joints)
        gates.update({j: own[:, k] for k, j in enumerate(joints) if j in noise})
    return {j: noise[j] * (scale * gates[j])[:, None] for j in noise}


def soft_limit_angle(aa: np.ndarray, knee: float, cap: float) -> np.ndarray:
    """(..., 3) axis-angle rotations with their angles eased above ``knee`` towards ``cap`` (same axes; the map
    is continuous with slope <= 1, so it never adds a jump)."""
    angle = np.linalg.norm(aa, axis=-1, keepdims=True)
    eased = knee + (cap - knee) * np.tanh((angle - knee) / (cap - knee))
    return aa * np.where(angle > knee, eased / np.maximum(angle, 1e-9), 1.0)


def _aa(v) -> np.ndarray:
    return axis_angle_to_matrix(np.asarray(v, np.float64))


class BodySolver:
    """Turns posture, arm tracks and head offsets into local joint rotations (T, 55, 3, 3)."""

    def __init__(self, skeleton: Skeleton, fps: float):
        self.skeleton, self.fps = skeleton, fps
        self.base = load_calibration().base_local_aa
        rest = skeleton.rest_joints.astype(np.float64)
        self.arm_chains, self.leg_chains = {}, {}
        for side, sign in (("left", 1.0), ("right", -1.0)):
            _, sh, el, wr, hip, kn, an, _ = SIDE_JOINTS[side]
            self.arm_chains[side] = TwoBoneChain(
                rest[el] - rest[sh],
                rest[wr] - rest[el],
                np.array([0.0, -sign, 0.0]),
                min_flex_rad=ARM_MIN_FLEX_RAD,
                max_flex_step_rad=ARM_MAX_FLEX_STEP_RAD,
                soft_reach=ARM_SOFT_REACH,
            )
            self.leg_chains[side] = TwoBoneChain(
                rest[kn] - rest[hip],
                rest[an] - rest[kn],
                np.array([1.0, 0.0, 0.0]),
                min_flex_rad=0.05,
                max_flex_rad=1.2,
            )

    def _fk(self, local: np.ndarray, trans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        joints, transforms = forward_kinematics(self.skeleton, torch.from_numpy(local), torch.from_numpy(trans))
        return joints.numpy(), transforms[..., :3, :3].numpy()

    def solve(self, posture: Posture, arms: ArmTracks, head: np.ndarray, rest_wrist_y: float) -> np.ndarray:
        n = len(head)
        local = np.broadcast_to(np.eye(3), (n, NUM_JOINTS, 3, 3)).copy()
        local[:, 0] = _aa(posture.root_offset_aa) @ _aa(self.base[0])
        for k, j in enumerate(SPINE):
            local[:, j] = _aa(posture.spine_offset_aa[:, k]) @ _aa(self.base[j])
        neck, head_joint = NECK_HEAD
        local[:, neck] = _aa(NECK_SHARE * head) @ _aa(self.base[neck])
        local[:, head_joint] = _aa((1 - NECK_SHARE) * head) @ _aa(self.base[head_joint])
        raise_amount = np.clip((arms.wrist[..., 1] - rest_wrist_y) / 0.4, 0.0, 1.0)  # (T, 2)
        for s, (side, sign) in enumerate((("left", 1.0), ("right", -1.0))):
            lift = posture.collar_lift + 0.1 * raise_amount[:, s]
            local[:, SIDE_JOINTS[side][0]] = _aa(np.stack([0 * lift, 0 * lift, sign * lift], -1)) @ _aa(
                self.base[SIDE_JOINTS[side][0]]
            )
        joints, rots = self._fk(local, posture.trans)
        for s, (side, sign) in enumerate((("left", 1.0), ("right", -1.0))):
            self._solve_arm(local, joints, rots, arms, s, side, sign)
            self._solve_leg(local, joints, rots, posture, s, side, sign)
        self._collars_follow_arms(local, posture.trans)
        joints, rots = self._fk(local, posture.trans)
        for s, (side, sign) in enumerate((("left", 1.0), ("right", -1.0))):
            self._solve_arm(local, joints, rots, arms, s, side, sign)
        return local

    def _collars_follow_arms(self, local: np.ndarray, trans: np.ndarray) -> None:
        """Turns each collar by COLLAR_SHARE of its upper arm's swing from the arm's median direction (chest frame)."""
        joints, rots = self._fk(local, trans)
        sigma = COLLAR_SMOOTH_S * self.fps
        for side in ("left", "right"):
            collar, sh, el = SIDE_JOINTS[side][:3]
            upper = np.einsum("tji,tj->ti", rots[:, 9], joints[:, el] - joints[:, sh])  # (T, 3) chest frame
            upper /= np.linalg.norm(upper, axis=-1, keepdims=True)
            ref = np.median(upper, axis=0)
            ref /= np.linalg.norm(ref)
            axis = np.cross(ref, upper)  # (T, 3), length sin(angle)
            sin = np.linalg.norm(axis, axis=-1, keepdims=True)
            angle = np.arctan2(sin, (upper @ ref)[:, None])  # (T, 1)
            turn = COLLAR_SHARE * angle * axis / np.maximum(sin, 1e-9)  # (T, 3) axis-angle, chest frame
            local[:, collar] = _aa(gaussian_filter1d(turn, sigma, axis=0)) @ local[:, collar]

    def _solve_arm(self, local, joints, rots, arms: ArmTracks, s: int, side: str, sign: float) -> None:
        collar, sh, el, wr = SIDE_JOINTS[side][:4]
        chest_rot, chest_pos = rots[:, 9], joints[:, 9]
        target = chest_pos + np.einsum("tij,tj->ti", chest_rot, arms.wrist[:, s])
        ones = np.ones(len(target))
        pole_local = np.stack(
            [sign * (POLE_OUT + arms.elbow_out[:, s]), POLE_DOWN * ones, -ones], -1
        )  # elbow out and back
        pole = np.einsum("tij,tj->ti", chest_rot, pole_local)
        chain = self.arm_chains[side]
        local[:, sh], theta = chain.solve(joints[:, sh], rots[:, collar], target, pole)
        forearm = chain.bone_c / np.linalg.norm(chain.bone_c)
        twist = -sign * arms.supination[:, s, None] * forearm  # (T, 3): supination turns the palm up
        local[:, el] = _aa(theta[:, None] * chain.hinge_axis) @ _aa(0.5 * twist)
        flex = np.zeros((len(target), 3))
        flex[:, 2] = -sign * arms.flex[:, s]
        local[:, wr] = _aa(0.5 * twist) @ _aa(flex)

    def _solve_leg(self, local, joints, rots, posture: Posture, s: int, side: str, sign: float) -> None:
        hip, knee, ankle = SIDE_JOINTS[side][4:7]
        pelvis_rot = rots[:, 0]
        pole = np.einsum("tij,j->ti", pelvis_rot, np.array([sign * 0.15, 0.0, 1.0]))
        chain = self.leg_chains[side]
        local[:, hip], theta = chain.solve(joints[:, hip], pelvis_rot, posture.ankles[:, s], pole)
        local[:, knee] = _aa(theta[:, None] * chain.hinge_axis)
        shin = pelvis_rot @ local[:, hip] @ local[:, knee]  # (T, 3, 3) knee world rotation
        foot = rotation_about_y(np.full(len(theta), posture.foot_yaw[s]))
        local[:, ankle] = np.swapaxes(shin, -1, -2) @ foot


def synthesize_agent_motion(
    cfg: SynthConfig,
    rng: np.random.Generator,
    conv: Conversation,
    skeleton: Skeleton | None = None,
    micro: dict[int, MicroNoise] | None = None,
) -> AgentMotion:
    """The agent's motion; ``micro`` overrides the calibrated micro-motion (``{}``: none, as the fit needs)."""
    skeleton = skeleton or Skeleton.default()
    fps = cfg.motion_fps
    n = int(round(conv.duration_s * fps))
    speaking = speaking_frames(conv, n, fps)
    energy = LISTENING_ENERGY + (1 - LISTENING_ENERGY) * gaussian_filter1d(speaking, 8)
    env = speech_envelope(conv.channels[AGENT], conv.sample_rate_hz, n, fps)
    stance_rng = np.random.default_rng(rng.integers(2**63))  # its own stream: the stance's steps leave the rest alone
    posture = plan_posture(stance_rng, n, fps, energy, skeleton)
    arms = plan_arms(cfg, rng, conv, n, fps, energy)
    head, nods = plan_head(rng, conv, n, fps, energy, env, speaking)
    expressions = plan_face(rng, conv, n, fps, env, nods)
    params = load_calibration().micro_motion if micro is None else micro
    offsets = micro_motion(rng, n, fps, params, micro_motion_scale(speaking, env, fps))
    if 0 in offsets:  # the pelvis turns before the legs are solved, so the feet stay planted
        root = offsets.pop(0)
        angle = np.maximum(np.linalg.norm(root, axis=-1, keepdims=True), 1e-9)
        eased = ROOT_MICRO_MAX_RAD * np.tanh(angle / ROOT_MICRO_MAX_RAD)
        posture.root_offset_aa = posture.root_offset_aa + root * (eased / angle)
    solver = BodySolver(skeleton, fps)
    # the turned pelvis moves the hips: lowered where a leg would otherwise lock straight (the ankle then flips)
    root_rot = _aa(posture.root_offset_aa) @ _aa(solver.base[0])
    posture.trans[:, 1] = np.minimum(
        posture.trans[:, 1], highest_pelvis(skeleton, posture.trans[:, [0, 2]], posture.ankles, root_rot)
    )
    local = solver.solve(posture, arms, head, rest_wrist_y=float(arms.wrist[0, 0, 1]))
    gesture_local = (
        local.copy()
    )  # what the codecs model: the agent's runtime layer adds the rest (gesture.layers.micro_motion)
    for j, offset in offsets.items():
        sign = ELBOW_SIDES.get(j)
        scale = 1.0 if sign is None else forearm_forward_scale(local[:, j], offset, sign)[:, None]
        local[:, j] = local[:, j] @ _aa(scale * offset)
        if j not in LAYERED_MICRO_JOINTS:
            gesture_local[:, j] = local[:, j]
    local = PostureReflexes(fps).step(local)  # on the layered joints: the runtime layer runs them after its noise
    poses, gesture_poses = (finish_poses(m, solver.base[22], env, arms) for m in (local, gesture_local))
    return AgentMotion(
        poses=poses,
        trans=posture.trans.astype(np.float32),
        expressions=expressions,
        vad=activity_frames(conv.words_of(AGENT), n, fps),
        user_vad=activity_frames(conv.words_of(USER), n, fps),
        planted=posture.planted.astype(np.uint8),
        gesture_poses=gesture_poses,
    )


def finish_poses(local: np.ndarray, jaw_rest: np.ndarray, env: np.ndarray, arms: ArmTracks) -> np.ndarray:
    """(T, 55, 3, 3) local rotations -> (T, 55, 3) float32 axis-angle within the soft joint limits, with the jaw
    following the speech envelope ``env`` and the planned hand shapes."""
    poses = matrix_to_axis_angle(local)  # (T, 55, 3)
    for j, (knee, cap) in JOINT_SOFT_LIMITS_RAD.items():
        poses[:, j] = soft_limit_angle(poses[:, j], knee, cap)
    poses[:, 22] = jaw_rest + np.stack([JAW_OPEN_RAD * env, 0 * env, 0 * env], -1)
    poses[:, 23:25] = 0.0
    poses[:, 25:55] = blend_hands(arms.hand)
    return poses.astype(np.float32)
