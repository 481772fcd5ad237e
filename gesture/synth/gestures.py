"""The agent's arm gestures: a planner that turns the agent's sentences into keyed arm tracks.

Per sentence the agent may gesture (``gesture_prob``); it picks a family (beat, open-palm presentation,
deictic pointing, two-handed size/shape, self-adaptor), the hands (right, left or both) and an amplitude.
Strokes land on the energy peaks of stressed words (at most one per 0.45 s): the stroke key is a
minimum-jerk stop, so the wrist's speed minimum falls on the stressed syllable. The hands are prepared
before the first stroke, hold through short pauses and retract to rest when the next sentence is far
away or the user barges in.

Arm state per side, in the chest (spine3) frame, x to the body's left, y up, z forward (right side mirrored):
wrist target (3), elbow swing outwards (1), palm supination (1: 0 palms face each other, >0 palm up),
wrist flexion (1), hand shape weights (4, see hands.HAND_SHAPES).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gesture.synth.calibration import load_calibration
from gesture.synth.config import GESTURE_FAMILIES, SynthConfig
from gesture.synth.conversation import AGENT, Conversation
from gesture.synth.hands import shape_weights
from gesture.synth.tracks import KeyTrack, smooth_noise

SIDES = (1.0, -1.0)  # left, right: the sign of x in the chest frame
MIN_STROKE_GAP_S = 0.45
# The gesture space against the real clip's wrist percentiles (chest frame); chosen by the realism measures of the
# agent driven by the clip's speech (gesture.eval.realism): the real speaker keeps the upper arms near the body and
# moves the forearms, so hands rest low, gesture high in front, and spread sideways little.
REST_ABOVE_P5_M = 0.0
CENTRE_ABOVE_MEDIAN_M = 0.08
CENTRE_WIDTH = 0.85
SIZE_WIDTH_M = (0.08, 0.25)
RETRACT_GAP_S = 1.0  # the hands go down when the next sentence is further away than this
CHANNELS = ("wrist", "elbow_out", "supination", "flex", "hand")
MAX_RATE = {"wrist": 0.8, "elbow_out": 1.5, "supination": 4.0, "flex": 3.0, "hand": 4.0}  # units/s per segment


def mirror(v, side: float) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return np.array([side * v[0], v[1], v[2]])


def gesture_space() -> tuple[np.ndarray, np.ndarray]:
    """Left-side rest and centre wrist positions in the chest frame, from the BEAT2 percentiles."""
    w = load_calibration().wrist_chest_m  # (side, percentile 5/50/95, xyz)
    left = (w[0] + w[1] * np.array([-1.0, 1.0, 1.0])[None]) / 2  # mirror-averaged (3 pct, 3)
    rest = np.array([0.8 * left[1, 0], left[0, 1] + REST_ABOVE_P5_M, left[0, 2] + 0.06])
    centre = np.array([CENTRE_WIDTH * left[1, 0], left[1, 1] + CENTRE_ABOVE_MEDIAN_M, left[1, 2] + 0.03])
    return rest, centre


@dataclass
class ArmTracks:
    wrist: np.ndarray  # (T, 2, 3) chest frame
    elbow_out: np.ndarray  # (T, 2)
    supination: np.ndarray  # (T, 2) rad
    flex: np.ndarray  # (T, 2) rad
    hand: np.ndarray  # (T, 2, 4)


class _Arm:
    REST_SUPINATION, REST_FLEX = 0.25, 0.1

    def __init__(self, side: float, rest: np.ndarray):
        self.side, self.rest = side, mirror(rest, side)
        initial = {
            "wrist": self.rest,
            "elbow_out": 0.0,
            "supination": self.REST_SUPINATION,
            "flex": self.REST_FLEX,
            "hand": shape_weights("relaxed"),
        }
        self.tracks = {name: KeyTrack(initial[name], MAX_RATE[name]) for name in CHANNELS}
        self.away = False  # not at rest

    @property
    def last_time(self) -> float:
        return self.tracks["wrist"].last_time

    def key(self, t: float, **values) -> None:
        """Key every channel at one time (unnamed channels hold); a too-fast change delays the key."""
        t = max(
            [t]
            + [
                track.last_time + np.linalg.norm(np.asarray(values[name]) - track.last_value) / track.max_rate
                for name, track in self.tracks.items()
                if name in values
            ]
        )
        for name, track in self.tracks.items():
            track.key(t, values[name] if name in values else track.last_value)
        self.away = True

    def retract(self, start_s: float, duration_s: float) -> None:
        if not self.away:
            return
        self.key(start_s)
        self.key(
            start_s + duration_s,
            wrist=self.rest,
            elbow_out=0.0,
            supination=self.REST_SUPINATION,
            flex=self.REST_FLEX,
            hand=shape_weights("relaxed"),
        )
        self.away = False


def pick_strokes(peaks: list[float], min_gap_s: float = MIN_STROKE_GAP_S) -> list[float]:
    strokes: list[float] = []
    for t in sorted(peaks):
        if not strokes or t - strokes[-1] >= min_gap_s:
            strokes.append(t)
    return strokes


class GesturePlanner:
    def __init__(self, cfg: SynthConfig, rng: np.random.Generator):
        self.cfg, self.rng = cfg, rng
        self.rest, self.centre = gesture_space()
        self.arms = [_Arm(s, self.rest) for s in SIDES]

    def _hands_for(self, family: str) -> list[_Arm]:
        if family in ("size", "adaptor"):
            return self.arms
        r = self.rng.random()
        if family == "deictic":
            return [self.arms[1] if r < 0.7 else self.arms[0]]
        return [self.arms[1]] if r < 0.4 else [self.arms[0]] if r < 0.65 else self.arms

    def _up_s(self, strokes: list[float], k: int) -> float:
        gap = strokes[k] - strokes[k - 1] if k else 0.6
        return min(self.rng.uniform(0.16, 0.26), 0.45 * gap)

    def _beat(self, arm: _Arm, strokes: list[float], amp: float) -> None:
        hold = mirror(self.centre + self.rng.normal(0, 0.03, 3) * (0.5, 1, 0.5), arm.side)
        hand = shape_weights("open", self.rng.uniform(0.2, 0.8))
        sup = self.rng.uniform(0.1, 0.8)
        up = hold + mirror((0.01 * amp, 0.07 * amp, -0.015 * amp), arm.side)
        down = hold + mirror((-0.015 * amp, -0.08 * amp, 0.025 * amp), arm.side)
        for k, ts in enumerate(strokes):
            arm.key(ts - self._up_s(strokes, k), wrist=up, supination=sup, hand=hand, flex=0.0, elbow_out=0.1 * amp)
            arm.key(ts, wrist=down, flex=0.25 * amp)

    def _presentation(self, arm: _Arm, strokes: list[float], amp: float) -> None:
        hold = mirror(self.centre + (0.04 * amp, 0.0, 0.03 * amp), arm.side)
        offer = hold + mirror((0.09 * amp, 0.04, 0.07 * amp), arm.side)
        arm.key(strokes[0] - self._up_s(strokes, 0) - 0.1, wrist=hold, supination=0.5, hand=shape_weights("open", 0.6))
        arm.key(strokes[0], wrist=offer, supination=self.rng.uniform(1.0, 1.4), hand=shape_weights("open"), flex=-0.1)
        for k in range(1, len(strokes)):
            arm.key(strokes[k] - self._up_s(strokes, k), wrist=offer + (0, 0.035 * amp, 0))
            arm.key(strokes[k], wrist=offer - (0, 0.03 * amp, 0))

    def _deictic(self, arm: _Arm, strokes: list[float], amp: float) -> None:
        targets = ((0.12, 0.02, 0.44), (0.28, 0.0, 0.32), (0.14, 0.1, 0.42), (0.04, -0.08, 0.2))
        aim = mirror(targets[int(self.rng.integers(len(targets)))], arm.side) + self.rng.normal(0, 0.02, 3)
        arm.key(
            strokes[0] - 0.15,
            wrist=aim - mirror((0.0, 0.0, 0.06), arm.side),
            hand=shape_weights("point", 0.7),
            supination=-0.3,
            elbow_out=0.3,
        )
        arm.key(strokes[0], wrist=aim, hand=shape_weights("point"), flex=-0.15)
        for k in range(1, len(strokes)):
            arm.key(strokes[k] - self._up_s(strokes, k), wrist=aim - (0, 0, 0.04 * amp))
            arm.key(strokes[k], wrist=aim)

    def _size(self, arm: _Arm, strokes: list[float], amp: float, widths: np.ndarray, heights: np.ndarray) -> None:
        for k, ts in enumerate(strokes):
            base = np.array([widths[k], heights[k], 0.3])
            arm.key(
                ts - self._up_s(strokes, k),
                wrist=mirror(base + (0.03, 0.03, 0.0), arm.side),
                supination=0.0,
                hand=shape_weights("open", 0.85),
                flex=0.0,
                elbow_out=0.2,
            )
            arm.key(ts, wrist=mirror(base - (0.0, 0.02 * amp, 0.0), arm.side))

    def _adaptor(self, arm: _Arm, strokes: list[float], amp: float) -> None:
        clasp = mirror((0.075, -0.27, 0.2), arm.side)
        arm.key(
            strokes[0] - 0.2, wrist=clasp, supination=0.1, hand=shape_weights("fist", 0.45), flex=0.15, elbow_out=0.0
        )
        for k in range(1, len(strokes)):
            arm.key(strokes[k] - self._up_s(strokes, k), wrist=clasp + (0, 0.015 * amp, 0.0))
            arm.key(strokes[k], wrist=clasp)

    def _sympathetic(self, arm: _Arm, strokes: list[float]) -> None:
        """The free hand half-rises and echoes the strokes faintly."""
        hold = mirror(0.6 * self.rest + 0.4 * self.centre, arm.side)
        arm.key(max(strokes[0] - 0.6, arm.last_time + 0.05))
        arm.key(strokes[0] - 0.15, wrist=hold, hand=shape_weights("open", 0.2))
        for k in range(1, len(strokes)):
            arm.key(strokes[k] - self._up_s(strokes, k), wrist=hold + (0, 0.015, 0))
            arm.key(strokes[k], wrist=hold - (0, 0.015, 0))

    def _gesture(self, family: str, strokes: list[float]) -> list[_Arm]:
        amp = self.rng.uniform(*self.cfg.amplitude)
        hands = self._hands_for(family)
        widths = self.rng.uniform(*SIZE_WIDTH_M, len(strokes)) * (0.6 + 0.4 * amp)
        heights = self.rng.uniform(-0.2, 0.0, len(strokes))
        for arm in hands:
            prep = strokes[0] - self.rng.uniform(0.35, 0.6)
            arm.key(max(prep, arm.last_time + 0.05))  # hold where the hand is until the preparation
            if family == "size":
                self._size(arm, strokes, amp, widths, heights)
            else:
                getattr(self, f"_{family}")(arm, strokes, amp)
        return hands

    def plan(self, conv: Conversation, n_frames: int, fps: float) -> ArmTracks:
        sentences = [(a, b, turn) for turn in conv.turns_of(AGENT, "turn") for a, b in turn.sentence_spans_s]
        peaks = [w.peak_s for w in conv.words_of(AGENT) if w.stressed]
        all_peaks = [w.peak_s for w in conv.words_of(AGENT)]
        weights = np.asarray(self.cfg.family_weights) / sum(self.cfg.family_weights)
        for i, (a, b, turn) in enumerate(sentences):
            next_a = sentences[i + 1][0] if i + 1 < len(sentences) else np.inf
            strokes = (
                pick_strokes([p for p in peaks if a <= p < b]) or pick_strokes([p for p in all_peaks if a <= p < b])[:1]
            )
            if strokes and self.rng.random() < self.cfg.gesture_prob:
                family = GESTURE_FAMILIES[int(self.rng.choice(len(GESTURE_FAMILIES), p=weights))]
                for arm in self.arms:  # a hand left up by the previous gesture and not used now goes down
                    if arm.away:
                        arm.retract(max(arm.last_time, strokes[0] - 0.9), 0.6)
                active = self._gesture(family, strokes)
                for arm in self.arms:
                    if arm not in active:
                        self._sympathetic(arm, strokes)
            cut = turn.interrupted and b >= turn.end_s - 1e-6
            end = turn.end_s + self.rng.uniform(0.05, 0.2) if cut else b + self.rng.uniform(0.15, 0.45)
            if cut or next_a - end > RETRACT_GAP_S:
                for arm in self.arms:
                    arm.retract(max(end, arm.last_time), self.rng.uniform(0.5, 0.9))
        self._listening_adaptors(conv, sentences)
        return self._evaluate(n_frames, fps)

    def _listening_adaptors(self, conv: Conversation, sentences) -> None:
        """Long listening stretches: sometimes the hands clasp in front until the agent speaks again."""
        starts = [a for a, _, _ in sentences] + [conv.duration_s]
        for end_prev, start_next in zip([0.0] + [b for _, b, _ in sentences], starts):
            if start_next - end_prev < 5.0 or self.rng.random() > 0.3:
                continue
            t0 = max(end_prev + self.rng.uniform(1.0, 2.0), max(arm.last_time for arm in self.arms) + 0.2)
            if start_next - t0 < 3.0:
                continue
            for arm in self.arms:
                arm.key(t0)
                self._adaptor(arm, [t0 + 0.8], 0.5)
                arm.retract(start_next - 1.2, 0.6)

    def _evaluate(self, n_frames: int, fps: float) -> ArmTracks:
        times = np.arange(n_frames) / fps
        out = {name: np.stack([arm.tracks[name].evaluate(times) for arm in self.arms], 1) for name in CHANNELS}
        return ArmTracks(
            wrist=out["wrist"],
            elbow_out=out["elbow_out"][..., 0],
            supination=out["supination"][..., 0],
            flex=out["flex"][..., 0],
            hand=out["hand"],
        )


def plan_arms(
    cfg: SynthConfig, rng: np.random.Generator, conv: Conversation, n_frames: int, fps: float, energy: np.ndarray
) -> ArmTracks:
    """Arm tracks plus a little organic drift of the wrists, scaled by ``energy`` (T,)."""
    tracks = GesturePlanner(cfg, rng).plan(conv, n_frames, fps)
    drift = smooth_noise(rng, n_frames, fps, 0.4, 6).reshape(n_frames, 2, 3) * 0.008
    tracks.wrist = tracks.wrist + drift * energy[:, None, None]
    return tracks
