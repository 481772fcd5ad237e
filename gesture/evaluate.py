"""Evaluate a predicted motion against ground truth:
``python -m gesture.evaluate --motion pred.npz --gt gt.npz --wav speech.wav --json``;
the shipped default agent's quality report: ``python -m gesture.evaluate --suite default --json`` (gesture.suite),
and its realism against a real speaker: ``python -m gesture.evaluate --suite real --json`` (gesture.realism).

Motion files: BEAT2-style npz (poses (T, 165) or (T, 55, 3), trans, expressions; rate from
``mocap_frame_rate`` or ``fps``, default 25). The protocol is described in gesture.metrics.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Optional, Sequence, Union

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from gesture import metrics as M  # noqa: E402
from gesture.data.errors import DataError  # noqa: E402
from gesture.fgd import FeatureEncoder, KineticGeometricEncoder, fgd  # noqa: E402

DEFAULT_MEAN_SPEED = Path(__file__).resolve().parents[2] / "shared" / "data" / "beat2" / "mean_vel_smplxflame_30.npy"


def evaluate_motion(
    pred: M.MotionClip,
    gt: M.MotionClip,
    speech: Optional[Union[M.SpeechAudio, np.ndarray]] = None,
    mean_speed: Optional[np.ndarray] = None,
    body: Optional[M.Body] = None,
    encoders: Sequence[FeatureEncoder] = (KineticGeometricEncoder(),),
    expression_dirs: Optional[np.ndarray] = None,
    onsets_s: Optional[np.ndarray] = None,
) -> dict:
    """Every metric of one prediction/GT pair by the reference protocol (gesture.metrics), over every frame.

    ``speech``: a SpeechAudio at its file's rate, or a plain array of 16 kHz samples. BeatAlign needs the
    normaliser ``mean_speed`` and either ``speech`` or ready ``onsets_s`` (seconds from the beat window's start,
    as ``M.beat_align_onsets_s`` gives them). ``body``: an SMPL-X body (shaped by the GT's betas) or a skeleton;
    the built-in skeleton by default.
    """
    pair = M.prepare_pair(pred, gt, body)
    pj, gj = pair.pred_joints, pair.gt_joints
    out = {
        "frames_30fps": int(len(pj)),
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


def _encoders(args) -> list:
    encoders: list = [KineticGeometricEncoder()]
    if args.fgd_encoder:
        from gesture.fgd_vaeskconv import load_vaeskconv_encoder

        encoders.append(load_vaeskconv_encoder(args.fgd_encoder))
    return encoders


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--suite" in argv:
        at = argv.index("--suite")
        if argv[at + 1:at + 2] == ["real"]:  # the agent against a real speaker (gesture.realism)
            from gesture.realism import main as realism_main

            return realism_main(argv[:at] + argv[at + 2:])
        from gesture.suite import main as suite_main  # the default agent's quality report (gesture.suite)

        return suite_main(argv)
    parser = argparse.ArgumentParser(description="Gesture metrics of a predicted motion against ground truth.")
    parser.add_argument("--motion", required=True, help="predicted motion npz")
    parser.add_argument("--gt", required=True, help="ground-truth motion npz")
    parser.add_argument("--wav", help="the speech (for BeatAlign)")
    parser.add_argument("--mean-vel", default=str(DEFAULT_MEAN_SPEED), help="BEAT2 mean_vel_smplxflame_30.npy")
    parser.add_argument("--smplx-model", help="SMPL-X-format body (npz/pkl, any number of shape and expression "
                        "components): joints shaped by the GT's betas, face MSE on its vertices")
    parser.add_argument("--smplx-shape-components", type=int,
                        help="shape components of the body file (default: 300 if it has >= 400 components, else 10)")
    parser.add_argument("--fgd-encoder", help="BEAT2 AESKConv_240_100.bin for the learned FGD")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        pred, gt = M.load_motion_clip(args.motion), M.load_motion_clip(args.gt)
        speech = M.load_speech(args.wav) if args.wav else None
        mean_speed = M.load_mean_speed(args.mean_vel) if args.wav else None
        body = M.SmplxBody(args.smplx_model, args.smplx_shape_components) if args.smplx_model else None
        dirs = body.expression_dirs if body is not None and body.expression_dirs.shape[-1] else None
        result = evaluate_motion(pred, gt, speech, mean_speed, body, _encoders(args), dirs)
    except (DataError, ValueError) as err:
        print(f"error: {_one_line(err)}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in result.items()}))
    else:
        for key, value in result.items():
            print(f"{key:28s} {value:.6g}" if isinstance(value, float) else f"{key:28s} {value}")
    return 0


def _one_line(err: Exception) -> str:
    return " ".join(str(err).split())


if __name__ == "__main__":
    sys.exit(main())
