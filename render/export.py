"""python -m render.export MOTION.npz --bvh OUT.bvh --glb OUT.glb: the agent's motion in files other tools open.

MOTION.npz is BEAT2's layout, as the gesture stage writes it (`<run dir>/motion.npz`) and
`examples/motion_client.py --save` does: `poses` (T, 165) or (T, 55, 3) axis-angle, `trans` (T, 3), optional
`expressions` (T, 100) and `mocap_frame_rate` (default 25).

- `--bvh`: the SMPL-X skeleton (rest offsets of the built-in body, or of `--body-model`), ZYX Euler angles,
  centimetres, at the motion's frame rate (render.bvh).
- `--glb`: the built-in avatar (or the SMPL-X model of `--body-model`) with its skin, 52 ARKit morph targets and
  the motion as an animation: joint rotations, root translation and the ARKit weights (render.gltf).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ecas.core.body import NUM_EXPRESSIONS, NUM_JOINTS
from gesture.body.skeleton import PARENTS, Skeleton
from render.bvh import write_bvh
from render.gltf import Motion, write_avatar_glb

DEFAULT_FPS = 25.0


def load_motion(path: str | Path) -> Motion:
    """A motion npz (see the module docstring); a missing key or wrong shape raises ValueError naming it."""
    with np.load(path) as data:
        if "poses" not in data or "trans" not in data:
            raise ValueError(f"{path}: needs 'poses' and 'trans' (BEAT2's npz layout); it has {sorted(data.files)}")
        poses = np.asarray(data["poses"], np.float64)
        n = len(poses)
        if poses.size != n * NUM_JOINTS * 3:
            raise ValueError(f"{path}: poses must be (T, {NUM_JOINTS * 3}) or (T, {NUM_JOINTS}, 3), got {poses.shape}")
        trans = np.asarray(data["trans"], np.float64)
        if trans.shape != (n, 3):
            raise ValueError(f"{path}: trans must be ({n}, 3), got {trans.shape}")
        expressions = np.zeros((n, NUM_EXPRESSIONS))
        if "expressions" in data:
            expressions = np.asarray(data["expressions"], np.float64)[:, :NUM_EXPRESSIONS]
            if len(expressions) != n:
                raise ValueError(f"{path}: expressions has {len(expressions)} frames, poses {n}")
        fps = float(data["mocap_frame_rate"]) if "mocap_frame_rate" in data else DEFAULT_FPS
    return Motion(poses.reshape(n, NUM_JOINTS, 3), trans, expressions, fps)


def _body(body_model: str | None):
    if body_model:
        from render.body_model import load_smplx_model

        return load_smplx_model(body_model)
    from render.avatar import build_avatar

    return build_avatar()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="ecas export", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("motion", type=Path, help="motion npz (BEAT2 layout)")
    p.add_argument("--bvh", type=Path, metavar="OUT.bvh", help="write the motion as BVH")
    p.add_argument("--glb", type=Path, metavar="OUT.glb", help="write the avatar with the motion as glTF binary")
    p.add_argument("--body-model", metavar="SMPLX_*.npz", help="a real SMPL-X model instead of the built-in avatar")
    args = p.parse_args(argv)
    if not (args.bvh or args.glb):
        p.error("give --bvh and/or --glb")
    try:
        motion = load_motion(args.motion)
    except (OSError, ValueError) as err:
        p.error(str(err))
    if args.bvh:
        if args.body_model:
            model = _body(args.body_model)
            rest = model.j_regressor @ model.v_template
        else:
            rest = Skeleton.default().rest_joints
        write_bvh(args.bvh, motion.poses, motion.trans, np.asarray(rest, np.float64), tuple(PARENTS), motion.fps)
        print(f"{args.bvh}: {len(motion.poses)} frames at {motion.fps:g} fps, {NUM_JOINTS} joints")
    if args.glb:
        write_avatar_glb(args.glb, _body(args.body_model), motion)
        print(f"{args.glb}: the avatar with {len(motion.poses)} frames of animation and ARKit weights")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
