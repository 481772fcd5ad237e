"""What the reduced-precision inference copies cost in quality (`python -m bench.codec --quality --json`).

- `random_codes_error`: the largest |feature| difference between each prepared copy's streaming decode and the
  float32 codec's offline decode, on random codes, for the three codecs of one size.
- `clip_mpjpe_mm`: a real motion clip encoded by the trained codecs, then stream-decoded by the float32 codecs
  and by each prepared copy; the MPJPE (mm, 55 FK joints, zero translation, 25 fps) of every decode against
  the clip, as `gesture.eval.suite.codec_mpjpe_mm` measures it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from ecas.core.body import REGIONS
from ecas.core.timing import MOTION_FPS
from gesture.body.motion import canonicalize
from gesture.body.regions import features_to_motion, motion_to_features
from gesture.body.skeleton import Skeleton
from gesture.codec.build import build_codec
from gesture.codec.config import CodecConfig
from gesture.codec.inference import inference_codec
from gesture.codec.model import GestureCodec
from gesture.codec.streaming import StreamingDecoder
from gesture.eval import metrics as M


def stream_decode(codec: GestureCodec, codes: torch.Tensor) -> torch.Tensor:
    """codes (B, K, S) -> (B, 2S, nfeats) float32, one StreamingDecoder step per column."""
    with StreamingDecoder(codec, batch_size=codes.shape[0]) as decoder:
        return torch.cat([decoder.step(codes[..., s : s + 1]) for s in range(codes.shape[-1])], dim=1)


@torch.no_grad()
def random_codes_error(config: CodecConfig, dtypes: Sequence[str], steps: int = 40, seed: int = 0) -> dict:
    """{dtype: {region: max |prepared stream - float32 offline|}, "scale": {region: max |float32 offline|}}."""
    torch.manual_seed(seed)
    errors: dict = {dtype: {} for dtype in dtypes}
    errors["scale"] = {}
    for region in REGIONS:
        codec = build_codec(config, region).eval()
        codes = torch.randint(0, config.codebook_size, (1, codec.n_q, steps))
        offline = codec.decode(codes)
        errors["scale"][region] = float(offline.abs().max())
        for dtype in dtypes:
            errors[dtype][region] = float((stream_decode(inference_codec(codec, dtype), codes) - offline).abs().max())
    return errors


@torch.no_grad()
def clip_mpjpe_mm(
    codecs: Mapping[str, GestureCodec], clip_path: Path, dtypes: Sequence[str], skeleton: Skeleton | None = None
) -> dict:
    """MPJPE (mm) of the clip through encode -> stream decode, by the float32 codecs and by each prepared copy."""
    skeleton = skeleton or Skeleton.default()
    clip = M.load_motion_clip(clip_path).at_fps(MOTION_FPS)
    poses, trans = canonicalize(clip.poses, clip.trans)
    features = motion_to_features(poses, trans, clip.expressions, MOTION_FPS)  # region -> (T, F)
    frames = len(features["upper"]) // 2 * 2
    codes = {r: codecs[r].eval().encode(torch.from_numpy(features[r][None, :frames])) for r in REGIONS}
    gt_joints = M.joints_zero_translation(poses[:frames], skeleton)

    def decode_joints(decode) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        recon = {r: decode(r)[0].numpy() for r in REGIONS}
        pred, _, _ = features_to_motion(recon["upper"], recon["lower"], recon["face"])
        return M.joints_zero_translation(pred, skeleton), recon

    reference_joints, reference = decode_joints(lambda r: stream_decode(codecs[r], codes[r]))
    reference_mm = 1000 * M.mpjpe_m(reference_joints, gt_joints)
    result = {"clip": Path(clip_path).stem, "frames": frames, "float32_mpjpe_mm": reference_mm}
    for dtype in dtypes:
        prepared = {r: inference_codec(codecs[r], dtype) for r in REGIONS}
        joints, recon = decode_joints(lambda r: stream_decode(prepared[r], codes[r]))
        value_mm = 1000 * M.mpjpe_m(joints, gt_joints)
        result[dtype] = {
            "mpjpe_mm": value_mm,
            "mpjpe_change_mm": value_mm - reference_mm,
            "mpjpe_to_float32_decode_mm": 1000 * M.mpjpe_m(joints, reference_joints),
            "max_abs_feature_error": max(float(np.abs(recon[r] - reference[r]).max()) for r in REGIONS),
        }
    return result
