"""Reconstruction quality of a region codec: MPJPE (mm) of the 55 FK joints, and feature MSE."""

from __future__ import annotations

import torch

from ecas.core.body import JAW_JOINT, LOWER_JOINTS, REGION_JOINTS
from gesture.body.regions import FACE_JAW_SLICE, LOWER_ROT_SLICE
from gesture.body.rotation import geodesic_angle, rot6d_to_axis_angle, rot6d_to_matrix
from gesture.body.skeleton import Skeleton, forward_kinematics
from gesture.codec.data import MotionSequence
from gesture.codec.model import GestureCodec


def region_rot6d(features: torch.Tensor, region: str) -> torch.Tensor:
    """(T, nfeats) -> (T, J_region, 6)."""
    if region == "lower":
        return features[:, LOWER_ROT_SLICE].unflatten(-1, (len(LOWER_JOINTS), 6))
    if region == "face":
        return features[:, FACE_JAW_SLICE].unflatten(-1, (1, 6))
    return features.unflatten(-1, (-1, 6))


@torch.no_grad()
def reconstruct(codec: GestureCodec, features: torch.Tensor) -> torch.Tensor:
    """Offline encode -> decode of (T, nfeats) with all quantizer levels, in eval mode."""
    was_training = codec.training
    codec.eval()
    frames = features.shape[0] // codec.ratio * codec.ratio
    device = next(codec.parameters()).device
    out = codec.decode(codec.encode(features[None, :frames].to(device)))[0].cpu()
    codec.train(was_training)
    return out


@torch.no_grad()
def region_mpjpe_mm(poses: torch.Tensor, features: torch.Tensor, region: str, skeleton: Skeleton) -> float:
    """MPJPE over 55 joints, no translation, between `poses` (T, 55, 3) and the same poses with the
    region's joints taken from `features` (T', nfeats), T' <= T."""
    poses = poses[: features.shape[0]]
    edited = poses.clone()
    joints = list(REGION_JOINTS[region]) if region != "face" else [JAW_JOINT]
    edited[:, joints] = rot6d_to_axis_angle(region_rot6d(features, region)).to(poses.dtype)
    reference, _ = forward_kinematics(skeleton, poses)
    predicted, _ = forward_kinematics(skeleton, edited)
    return float((predicted - reference).norm(dim=-1).mean() * 1000)


@torch.no_grad()
def jaw_error_deg(target: torch.Tensor, recon: torch.Tensor) -> float:
    """Mean geodesic jaw error in degrees between face features (T, 106)."""
    angle = geodesic_angle(rot6d_to_matrix(target[:, FACE_JAW_SLICE]), rot6d_to_matrix(recon[:, FACE_JAW_SLICE]))
    return float(torch.rad2deg(angle).mean())


def evaluate(codec: GestureCodec, sequences: list[MotionSequence], region: str, skeleton: Skeleton) -> dict[str, float]:
    """Frame-weighted means over `sequences` of the codec's reconstruction errors: feature MSE, and
    MPJPE in mm (upper, lower: the jaw moves no joint) or the jaw angle in degrees (face)."""
    totals: dict[str, float] = {}
    frames = 0
    for sequence in sequences:
        target = sequence.features[region]
        recon = reconstruct(codec, target)
        n = recon.shape[0]
        errors = {"feature_mse": float((recon - target[:n]).pow(2).mean())}
        if region == "face":
            errors["jaw_error_deg"] = jaw_error_deg(target[:n], recon)
        else:
            errors["mpjpe_mm"] = region_mpjpe_mm(sequence.poses, recon, region, skeleton)
        for key, value in errors.items():
            totals[key] = totals.get(key, 0.0) + value * n
        frames += n
    return {**{k: v / max(frames, 1) for k, v in totals.items()}, "frames": frames}
