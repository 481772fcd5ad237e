"""Render speed: ms per frame of pose -> LBS -> upload -> render -> readback, and offline MP4 throughput.

    python -m bench.render --json [--frames 60] [--mp4-seconds 64]

For each GL platform (OSMesa, EGL; each in its own process, as PyOpenGL binds one platform per process) and
frame size (256², 512², 1280x720) it times the in-place vertex-buffer path next to the naive path that builds
a new pyrender Mesh every frame (and, on EGL, pyrender's default 4x MSAA), on the same BEAT2 poses in the
same run, alternating frame by frame; `cpu_median_ms` is the process CPU time per frame (all threads).
Then it renders the BEAT2 clip to
an MP4 at 512² (OSMesa) and reports the real-time factor. The machine is shared and timings are noisy:
compare the paths within one run, and read `load_avg`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ecas.core.paths import real_clip

SIZES = ((256, 256), (512, 512), (1280, 720))
PLATFORMS = ("osmesa", "egl")
PATHS = ("in_place", "new_mesh")


def _motion(n_frames: int):
    from render.play import load_motion_25fps

    clip_npz = real_clip().with_suffix(".npz")
    if clip_npz.is_file():
        poses, trans, expressions, _ = load_motion_25fps(clip_npz)
        return poses[:n_frames], trans[:n_frames], expressions[:n_frames]
    rng = np.random.default_rng(0)  # without the shared clip: smooth random motion around a standing pose
    poses = np.cumsum(rng.normal(0, 0.01, (n_frames, 55, 3)), axis=0).astype(np.float32)
    trans = np.tile(np.float32([0.0, 1.3, 0.0]), (n_frames, 1))
    return poses, trans, np.zeros((n_frames, 100), np.float32)


def _stats(times_s: list[float], cpu_s: list[float] | None = None) -> dict:
    ms = 1000 * np.asarray(times_s)
    out = {"median_ms": round(float(np.median(ms)), 2), "p95_ms": round(float(np.percentile(ms, 95)), 2), "n": len(ms)}
    if cpu_s is not None:  # CPU time of all this process's threads (llvmpipe's included): less load-dependent
        out["cpu_median_ms"] = round(float(np.median(1000 * np.asarray(cpu_s))), 2)
    return out


def time_platform(platform: str, n_frames: int, warmup: int = 5) -> dict:
    """{size: {in_place: stats, new_mesh: stats}} for one platform (runs in this process)."""
    import torch

    torch.set_num_threads(1)
    from render.avatar import build_avatar
    from render.view import AvatarView

    body = build_avatar()
    poses, trans, expressions = _motion(n_frames + warmup)
    out = {"vertices": body.n_vertices}
    paths = PATHS + (("in_place_msaa4",) if platform == "egl" else ())
    for width, height in SIZES:
        views = {
            path: AvatarView(
                body,
                width,
                height,
                platform=platform,
                in_place=path != "new_mesh",
                msaa_samples=4 if path.endswith("msaa4") else 0,
            )
            for path in paths
        }
        times: dict[str, list[float]] = {path: [] for path in paths}
        cpu: dict[str, list[float]] = {path: [] for path in paths}
        for i in range(n_frames + warmup):  # the paths alternate frame by frame, so they share the machine's load
            for path, view in views.items():
                t0, c0 = time.perf_counter(), time.process_time()
                image = view.frame(poses[i], trans[i], expressions[i])  # pose, LBS, upload, render, readback
                if i >= warmup:
                    times[path].append(time.perf_counter() - t0)
                    cpu[path].append(time.process_time() - c0)
                assert image.shape == (height, width, 3)
        for view in views.values():
            view.close()
        out[f"{width}x{height}"] = {path: _stats(times[path], cpu[path]) for path in paths}
    return out


def time_stages(n_frames: int = 40) -> dict:
    """Median ms of each stage at 512² on OSMesa: LBS, normals+upload+render+readback, H.264+AAC encode."""
    import torch

    torch.set_num_threads(1)
    from render.avatar import build_avatar
    from render.mp4 import Mp4Writer
    from render.view import AvatarView

    view = AvatarView(build_avatar(), 512, 512)
    poses, trans, expressions = _motion(n_frames)
    lbs, draw, encode = [], [], []
    with tempfile.TemporaryDirectory() as tmp, Mp4Writer(Path(tmp) / "stages.mp4", 512, 512) as writer:
        for i in range(n_frames):
            t0 = time.perf_counter()
            vertices, joints = view.pose(poses[i], trans[i], expressions[i])
            t1 = time.perf_counter()
            image = view.draw(vertices, joints)
            t2 = time.perf_counter()
            writer.write(image, np.zeros(960, np.float32))
            t3 = time.perf_counter()
            lbs.append(t1 - t0)
            draw.append(t2 - t1)
            encode.append(t3 - t2)
    view.close()
    return {"lbs": _stats(lbs), "render": _stats(draw), "encode": _stats(encode)}


def _run_worker(args: list[str]) -> dict:
    done = subprocess.run(
        [sys.executable, "-m", "bench.render", *args],
        capture_output=True,
        text=True,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )
    if done.returncode != 0:
        lines = [line for line in (done.stderr or done.stdout).splitlines() if "Error" in line or "error" in line]
        return {"error": lines[-1].strip() if lines else f"exit code {done.returncode}"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def mp4_throughput(seconds: float | None) -> dict:
    from render.play import render_motion

    clip_npz, clip_wav = real_clip().with_suffix(".npz"), real_clip().with_suffix(".wav")
    if not clip_npz.is_file():
        return {"error": f"{clip_npz} not present"}
    with tempfile.TemporaryDirectory() as tmp:
        stats = render_motion(
            clip_npz,
            clip_wav,
            Path(tmp) / "clip.mp4",
            width=512,
            height=512,
            max_frames=None if seconds is None else int(seconds * 25),
            progress=False,
        )
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in stats.items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="ecas bench render", description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--frames", type=int, default=60, help="timed frames per size and path")
    p.add_argument(
        "--mp4-seconds",
        type=float,
        default=20.0,
        help="seconds of the BEAT2 clip to encode for the real-time factor (0: skip, -1: the whole clip)",
    )
    p.add_argument("--worker", choices=PLATFORMS + ("stages", "mp4"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker in PLATFORMS:
        print(json.dumps(time_platform(args.worker, args.frames)))
        return 0
    if args.worker == "stages":
        print(json.dumps(time_stages()))
        return 0
    if args.worker == "mp4":
        print(json.dumps(mp4_throughput(None if args.mp4_seconds < 0 else args.mp4_seconds)))
        return 0
    from bench.machine import machine_report  # here, not at the top: the render workers need no torch

    result = {"machine": machine_report(), "load_avg_before": os.getloadavg()[0], "cpus": os.cpu_count()}
    result["platforms"] = {pf: _run_worker(["--worker", pf, "--frames", str(args.frames)]) for pf in PLATFORMS}
    result["stages_512_osmesa"] = _run_worker(["--worker", "stages"])
    if args.mp4_seconds:
        result["mp4_offline_512_osmesa"] = _run_worker(["--worker", "mp4", "--mp4-seconds", str(args.mp4_seconds)])
    result["load_avg_after"] = os.getloadavg()[0]
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        for platform, rows in result["platforms"].items():
            if "error" in rows:
                print(f"{platform}: unavailable ({rows['error']})")
                continue
            for size, paths in rows.items():
                if size != "vertices":
                    print(
                        f"{platform} {size}: in-place {paths['in_place']['median_ms']} ms "
                        f"(p95 {paths['in_place']['p95_ms']}), new mesh {paths['new_mesh']['median_ms']} ms"
                    )
        print(json.dumps({k: v for k, v in result.items() if k != "platforms"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
