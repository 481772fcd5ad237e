"""Evaluate a predicted motion against ground truth:
``python -m gesture.evaluate --motion pred.npz --gt gt.npz --wav speech.wav --json``;
the shipped default agent's quality report: ``python -m gesture.evaluate --suite default --json`` (gesture.suite).

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
from typing import Optional, Sequence

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from gesture import metrics as M  # noqa: E402
from gesture.data.audio import load_audio  # noqa: E402
from gesture.data.errors import DataError  # noqa: E402
from gesture.fgd import FeatureEncoder, KineticGeometricEncoder, fgd  # noqa: E402
from gesture.skeleton import Skeleton  # noqa: E402

DEFAULT_MEAN_SPEED = Path(__file__).resolve().parents[2] / "shared" / "data" / "beat2" / "mean_vel_smplxflame_30.npy"


def evaluate_motion(
    pred: M.MotionClip,
    gt: M.MotionClip,
    audio_16k: Optional[np.ndarray] = None,
    mean_speed: Optional[np.ndarray] = None,
    skeleton: Optional[Skeleton] = None,
    encoders: Sequence[FeatureEncoder] = (KineticGeometricEncoder(),),
    expression_dirs: Optional[np.ndarray] = None,
) -> dict:
    """Every metric of one prediction/GT pair; BeatAlign only when audio and the normaliser are given."""
    pair = M.prepare_pair(pred, gt, skeleton)
    pj, gj = M.trim(pair.pred_joints), M.trim(pair.gt_joints)
    pe, ge = M.trim(pair.pred_expressions), M.trim(pair.gt_expressions)
    out = {
        "frames_30fps": int(len(pj)),
        "mpjpe_mm": 1000 * M.mpjpe_m(pj, gj),
        "l1div": M.l1_divergence(pj),
        "l1div_gt": M.l1_divergence(gj),
        "face_expression_mse": M.expression_mse(pe, ge),
    }
    if expression_dirs is not None:
        out["face_vertex_mse"] = M.face_vertex_mse(pe, ge, expression_dirs)
    for encoder in encoders:
        out[f"fgd_{encoder.name}"] = fgd(encoder, M.trim(pair.pred_poses), pj, M.trim(pair.gt_poses), gj)
    if audio_16k is not None and mean_speed is not None:
        onsets = M.audio_onsets_s(audio_16k)
        for name, joints in (("", pair.pred_joints), ("_gt", pair.gt_joints)):
            out[f"beat_align{name}"] = M.beat_align(joints, onsets, mean_speed, reference_quirk=True)
            out[f"beat_align_corrected{name}"] = M.beat_align(joints, onsets, mean_speed, reference_quirk=False)
    return out


def _encoders(args) -> list:
    encoders: list = [KineticGeometricEncoder()]
    if args.fgd_encoder:
        from gesture.fgd_vaeskconv import load_vaeskconv_encoder

        encoders.append(load_vaeskconv_encoder(args.fgd_encoder))
    return encoders


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--suite" in argv:  # the default agent's quality report (gesture.suite)
        from gesture.suite import main as suite_main

        return suite_main(argv)
    parser = argparse.ArgumentParser(description="Gesture metrics of a predicted motion against ground truth.")
    parser.add_argument("--motion", required=True, help="predicted motion npz")
    parser.add_argument("--gt", required=True, help="ground-truth motion npz")
    parser.add_argument("--wav", help="the speech (for BeatAlign)")
    parser.add_argument("--mean-vel", default=str(DEFAULT_MEAN_SPEED), help="BEAT2 mean_vel_smplxflame_30.npy")
    parser.add_argument("--smplx-model", help="SMPL-X model npz: joints from its regressor, face MSE on its vertices")
    parser.add_argument("--fgd-encoder", help="BEAT2 AESKConv_240_100.bin for the learned FGD")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        pred, gt = M.load_motion_clip(args.motion), M.load_motion_clip(args.gt)
        audio = load_audio(args.wav, M.AUDIO_SAMPLE_RATE_HZ) if args.wav else None
        mean_speed = M.load_mean_speed(args.mean_vel) if args.wav else None
        skeleton = Skeleton.from_smplx_model(args.smplx_model) if args.smplx_model else None
        dirs = M.load_expression_dirs(args.smplx_model) if args.smplx_model else None
        result = evaluate_motion(pred, gt, audio, mean_speed, skeleton, _encoders(args), dirs)
    except (DataError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in result.items()}))
    else:
        for key, value in result.items():
            print(f"{key:28s} {value:.6g}" if isinstance(value, float) else f"{key:28s} {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
