"""Render a BEAT2/SMPL-X motion file to an MP4 with its sound.

    python -m render.play MOTION.npz [--wav SPEECH.wav] --mp4 OUT.mp4 [--camera full|upper|face] [--size 512]
    python -m render.play MOTION.npz --still OUT.png --start 12.0 [--camera face]

The motion (25 or 30 fps, or any rate) is resampled to 25 fps (slerp for rotations). The audio (any rate,
mono or stereo) is resampled to 24 kHz and cut or padded to exactly 960 samples per video frame. Encoding
runs in a second thread while the next frame renders.

Every input is checked before anything renders: a user mistake (a missing, empty or malformed motion file, a
missing or non-audio WAV, a bad size or time) gets one line and exit code 2.
"""

from __future__ import annotations

import argparse
import queue
import sys
import threading
import time
from pathlib import Path

import numpy as np

from ecas.core.threads import limit_threads
from ecas.core.timing import FRAME_SAMPLES, MOTION_FPS, SAMPLE_RATE_HZ
from render.renderer import CAMERA_PRESETS

EXIT_USAGE = 2
ARCHIVE_MAGIC = (b"PK\x03\x04", b"\x93NUMPY")  # an npz is a zip archive; np.load also reads a bare .npy


class UsageError(ValueError):
    """A bad argument or input file; one line."""


def load_motion_25fps(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """poses (T, 55, 3), trans (T, 3), expressions (T, 100), betas (B,) at 25 fps."""
    from gesture.body.rotation import resample_motion
    from gesture.data.beat2 import read_motion

    motion = read_motion(path)
    poses, trans, expressions = motion.poses, motion.trans, motion.expressions
    if abs(motion.fps - MOTION_FPS) > 1e-6:
        poses, trans, expressions = resample_motion(poses, trans, expressions, motion.fps, MOTION_FPS)
    return poses, trans, expressions, motion.betas


def frame_audio(wav_path: str | Path | None, n_frames: int) -> np.ndarray:
    """(n_frames, 960) float32: the speech at 24 kHz cut into one slice per video frame (silence without a WAV)."""
    total = n_frames * FRAME_SAMPLES
    pcm = np.zeros(total, np.float32)
    if wav_path is not None:
        from ecas.core.audio_file import load_audio

        speech = load_audio(wav_path, SAMPLE_RATE_HZ)[:total]
        pcm[: len(speech)] = speech
    return pcm.reshape(n_frames, FRAME_SAMPLES)


class EncoderThread:
    """Encodes (frame, audio) pairs on a worker thread; errors surface on `put` or `close`."""

    def __init__(self, writer) -> None:
        self.writer = writer
        self._queue: queue.Queue = queue.Queue(maxsize=8)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="mp4-encoder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            if self._error is None:
                try:
                    self.writer.write(*item)
                except BaseException as err:  # re-raised in the caller's thread
                    self._error = err

    def put(self, frame: np.ndarray, audio: np.ndarray) -> None:
        if self._error is not None:
            raise self._error
        self._queue.put((frame, audio))

    def close(self, commit: bool) -> None:
        self._queue.put(None)
        self._thread.join()
        if self._error is not None:
            self.writer.close(commit=False)
            raise self._error
        self.writer.close(commit=commit)


def render_motion(
    motion_path,
    wav_path,
    mp4_path,
    camera="full",
    width=512,
    height=512,
    platform="osmesa",
    body_model=None,
    max_frames=None,
    start_frame=0,
    progress=True,
) -> dict:
    """Render the motion file to `mp4_path`; returns timing numbers."""
    from render.mp4 import Mp4Writer
    from render.view import AvatarView, load_body

    poses, trans, expressions, betas = load_motion_25fps(motion_path)
    stop = len(poses) if max_frames is None else min(len(poses), start_frame + max_frames)
    audio = frame_audio(wav_path, len(poses))[start_frame:stop]
    body = load_body(body_model)
    # the motion's betas shape a real SMPL-X body; the mannequin's own shape space is not SMPL-X's
    view = AvatarView(body, width, height, camera=camera, platform=platform, betas=betas if body_model else None)
    encoder = EncoderThread(Mp4Writer(mp4_path, width, height))
    t0 = time.perf_counter()
    committed = False
    try:
        for i in range(start_frame, stop):
            encoder.put(view.frame(poses[i], trans[i], expressions[i]), audio[i - start_frame])
            if progress and (i - start_frame) % 250 == 0:
                print(f"frame {i - start_frame}/{stop - start_frame}", file=sys.stderr, flush=True)
        committed = True
    finally:
        encoder.close(commit=committed)
        view.close()
    wall_s = time.perf_counter() - t0
    n = stop - start_frame
    return {
        "frames": n,
        "video_s": n / MOTION_FPS,
        "wall_s": wall_s,
        "ms_per_frame": 1000 * wall_s / n,
        "x_real_time": (n / MOTION_FPS) / wall_s,
        "vertices": body.n_vertices,
    }


def render_still(
    motion_path, png_path, at_s: float, camera="full", width=512, height=512, platform="osmesa", body_model=None
) -> Path:
    """Render the frame at `at_s` seconds to a PNG (the camera tracks the second before it, as in the video)."""
    from PIL import Image

    from render.view import AvatarView, load_body

    poses, trans, expressions, betas = load_motion_25fps(motion_path)
    target = min(int(round(at_s * MOTION_FPS)), len(poses) - 1)
    view = AvatarView(
        load_body(body_model), width, height, camera=camera, platform=platform, betas=betas if body_model else None
    )
    try:
        for i in range(max(0, target - MOTION_FPS), target + 1):
            image = view.frame(poses[i], trans[i], expressions[i])
    finally:
        view.close()
    Image.fromarray(image).save(png_path)
    return Path(png_path)


def check_motion_file(path: str | Path) -> None:
    """The cheap checks np.load would turn into a traceback or a misleading message."""
    path = Path(path)
    if not path.exists():
        raise UsageError(f"{path}: no such file")
    if not path.is_file():
        raise UsageError(f"{path}: is not a file")
    with open(path, "rb") as f:
        head = f.read(8)
    if not head:
        raise UsageError(f"{path}: the file is empty")
    if not head.startswith(ARCHIVE_MAGIC):
        raise UsageError(f"{path}: not an npz archive (a BEAT2/SMPL-X motion file with poses, trans, expressions)")


def check_args(args: argparse.Namespace) -> tuple[int, int]:
    """Validate the numeric options; returns (width, height)."""
    if (args.width is None) != (args.height is None):
        raise UsageError("--width and --height go together")
    sizes = {"--size": args.size} if args.width is None else {"--width": args.width, "--height": args.height}
    for name, value in sizes.items():
        if value <= 0 or value % 2:
            raise UsageError(f"{name}: must be a positive even number of pixels (H.264 yuv420p), got {value}")
    width, height = (args.size, args.size) if args.width is None else (args.width, args.height)
    if args.start < 0:
        raise UsageError(f"--start: must be >= 0 seconds, got {args.start}")
    if args.seconds is not None and args.seconds <= 0:
        raise UsageError(f"--seconds: must be > 0, got {args.seconds}")
    return width, height


def check_inputs(args: argparse.Namespace) -> int:
    """Read the motion and the WAV once before rendering; returns the number of frames at 25 fps."""
    check_motion_file(args.motion)
    poses = load_motion_25fps(args.motion)[0]
    if args.start * MOTION_FPS >= len(poses):
        raise UsageError(f"--start {args.start}: the motion lasts {len(poses) / MOTION_FPS:.2f} s")
    if args.wav is not None:
        from ecas.core.audio_file import check_audio_file

        check_audio_file(args.wav)  # decoded once, later; a decoding problem is caught there
    return len(poses)


def main(argv=None) -> int:
    limit_threads()
    p = argparse.ArgumentParser(prog="ecas play", description=__doc__.splitlines()[0])
    p.add_argument("motion", help="BEAT2/SMPL-X npz with poses (T, 165), trans, expressions, mocap_frame_rate")
    p.add_argument("--wav", help="speech to put in the audio track (any rate, mono or stereo)")
    out = p.add_mutually_exclusive_group(required=True)
    out.add_argument("--mp4", help="output MP4 path")
    out.add_argument("--still", metavar="PNG", help="write one frame (at --start) as a PNG instead of a video")
    p.add_argument("--camera", choices=sorted(CAMERA_PRESETS), default="full")
    p.add_argument("--size", type=int, default=512, help="square frame size in pixels (default 512)")
    p.add_argument("--width", type=int, help="frame width (with --height; overrides --size)")
    p.add_argument("--height", type=int)
    p.add_argument("--platform", choices=("osmesa", "egl"), default="osmesa")
    p.add_argument("--body-model", help="a real SMPL-X model file (SMPLX_NEUTRAL_2020.npz); default: the mannequin")
    p.add_argument("--start", type=float, default=0.0, help="start time in seconds")
    p.add_argument("--seconds", type=float, help="render only this many seconds")
    args = p.parse_args(argv)

    from ecas.core.audio_file import AudioFileError
    from ecas.core.errors import DataError
    from render.body_model import BodyModelError
    from render.mp4 import Mp4Error, Mp4WriteError

    try:
        width, height = check_args(args)
        check_inputs(args)
        if args.still:
            render_still(
                args.motion,
                args.still,
                args.start,
                camera=args.camera,
                width=width,
                height=height,
                platform=args.platform,
                body_model=args.body_model,
            )
            print(f"{args.still}: frame at {args.start:.2f} s, camera {args.camera}")
            return 0
        stats = render_motion(
            args.motion,
            args.wav,
            args.mp4,
            camera=args.camera,
            width=width,
            height=height,
            platform=args.platform,
            body_model=args.body_model,
            max_frames=None if args.seconds is None else int(round(args.seconds * MOTION_FPS)),
            start_frame=int(round(args.start * MOTION_FPS)),
        )
    except Mp4WriteError as err:  # disk full, permission: not a usage mistake
        print(f"error: {err}", file=sys.stderr)
        return 1
    except (UsageError, DataError, AudioFileError, BodyModelError, Mp4Error) as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_USAGE
    print(
        f"{args.mp4}: {stats['frames']} frames ({stats['video_s']:.2f} s) in {stats['wall_s']:.1f} s, "
        f"{stats['ms_per_frame']:.1f} ms/frame, {stats['x_real_time']:.2f}x real time"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
