"""Evaluate a predicted motion against ground truth:
``ecas evaluate --motion pred.npz --gt gt.npz --wav speech.wav --json``;
the shipped default agent's quality report: ``ecas evaluate --suite default --json`` (gesture.eval.suite),
and its realism against a real speaker: ``ecas evaluate --suite real --json`` (gesture.eval.realism).

Motion files: BEAT2-style npz (poses (T, 165) or (T, 55, 3), trans, expressions; rate from
``mocap_frame_rate`` or ``fps``, default 25). The protocol is described in gesture.eval.metrics.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

from ecas.core.errors import DataError
from ecas.core.paths import data_root
from ecas.core.threads import limit_threads
from gesture.eval import metrics as M
from gesture.eval.fgd import KineticGeometricEncoder
from gesture.eval.scores import evaluate_motion

DEFAULT_MEAN_SPEED = data_root() / "beat2" / "mean_vel_smplxflame_30.npy"


def _encoders(args) -> list:
    encoders: list = [KineticGeometricEncoder()]
    if args.fgd_encoder:
        from gesture.eval.fgd_vaeskconv import load_vaeskconv_encoder

        encoders.append(load_vaeskconv_encoder(args.fgd_encoder))
    return encoders


def main(argv=None) -> int:
    limit_threads()
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--suite" in argv:
        at = argv.index("--suite")
        if argv[at + 1 : at + 2] == ["real"]:  # the agent against a real speaker (gesture.eval.realism)
            from gesture.eval.realism import main as realism_main

            return realism_main(argv[:at] + argv[at + 2 :])
        from gesture.eval.suite import main as suite_main  # the default agent's quality report (gesture.eval.suite)

        return suite_main(argv)
    parser = argparse.ArgumentParser(
        prog="ecas evaluate", description="Gesture metrics of a predicted motion against ground truth."
    )
    parser.add_argument("--motion", required=True, help="predicted motion npz")
    parser.add_argument("--gt", required=True, help="ground-truth motion npz")
    parser.add_argument("--wav", help="the speech (for BeatAlign)")
    parser.add_argument("--mean-vel", default=str(DEFAULT_MEAN_SPEED), help="BEAT2 mean_vel_smplxflame_30.npy")
    parser.add_argument(
        "--smplx-model",
        help="SMPL-X-format body (npz/pkl, any number of shape and expression "
        "components): joints shaped by the GT's betas, face MSE on its vertices",
    )
    parser.add_argument(
        "--smplx-shape-components",
        type=int,
        help="shape components of the body file (default: 300 if it has >= 400 components, else 10)",
    )
    parser.add_argument("--fgd-encoder", help="BEAT2 AESKConv_240_100.bin for the learned FGD")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
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
    raise SystemExit(main())
