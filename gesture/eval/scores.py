"""Every metric of one predicted motion against its ground truth, by the reference protocol (gesture.eval.metrics).

The command around it is gesture.eval.evaluate; the quality suite and the realism report call it per session.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gesture.eval import metrics as M
from gesture.eval.fgd import FeatureEncoder, KineticGeometricEncoder, fgd


def evaluate_motion(
    pred: M.MotionClip,
    gt: M.MotionClip,
    speech: M.SpeechAudio | np.ndarray | None = None,
    mean_speed: np.ndarray | None = None,
    body: M.Body | None = None,
    encoders: Sequence[FeatureEncoder] = (KineticGeometricEncoder(),),
    expression_dirs: np.ndarray | None = None,
    onsets_s: np.ndarray | None = None,
) -> dict:
    """Every metric of one prediction/GT pair by the reference protocol (gesture.eval.metrics), over every frame.

    ``speech``: a SpeechAudio at its file's rate, or a plain array of 16 kHz samples. BeatAlign needs the
    normaliser ``mean_speed`` and either ``speech`` or ready ``onsets_s`` (seconds from the beat window's start,
    as ``M.beat_align_onsets_s`` gives them). ``body``: an SMPL-X body (shaped by the GT's betas) or a skeleton;
    the built-in skeleton by default.
    """
    pair = M.prepare_pair(pred, gt, body)
    pj, gj = pair.pred_joints, pair.gt_joints
    out = {
        "frames_30fps": len(pj),
        "mpjpe_mm": 1000 * M.mpjpe_m(pj, gj),
        "l1div": M.l1_div(pj),
        "l1div_gt": M.l1_div(gj),
    }
    if pair.pred_expressions is not None:
        out["face_expression_mse"] = M.expression_mse(pair.pred_expressions, pair.gt_expressions)
        if expression_dirs is not None:
            out["face_vertex_mse"] = M.face_vertex_mse(pair.pred_expressions, pair.gt_expressions, expression_dirs)
    for encoder in encoders:
        out[f"fgd_{encoder.name}"] = fgd(encoder, pair.pred_poses, pj, pair.gt_poses, gj)
    if onsets_s is None and speech is not None:
        onsets_s = M.beat_align_onsets_s(speech, len(pj))
    if onsets_s is not None and mean_speed is not None:
        for name, joints in (("", pj), ("_gt", gj)):
            out[f"beat_align{name}"] = M.beat_align(joints, onsets_s, mean_speed, reference_quirk=True)
            out[f"beat_align_corrected{name}"] = M.beat_align(joints, onsets_s, mean_speed, reference_quirk=False)
    return out
