"""The README's three demo stills from a `make demo` run: the agent listening to the user, answering, and at its
fastest arm movement while it speaks.

    .venv/bin/python scripts/demo_stills.py [--mp4 out/demo.mp4] [--report out/demo-report] [--out docs]
"""

import argparse
import json
from pathlib import Path

import av
import numpy as np
from PIL import Image

ARM_JOINTS = slice(16, 22)  # shoulders, elbows, wrists of the SMPL-X body


def turns(report: Path, speaker: str) -> list[tuple[float, float]]:
    transcript = json.loads((report / "transcript.json").read_text())
    spans = [(t["start_s"], t["end_s"]) for t in transcript["turns"] if t["speaker"] == speaker]
    if not spans:
        raise SystemExit(f"{report}/transcript.json: no {speaker} turn")
    return spans


def fastest_arm_moment_s(report: Path, spans: list[tuple[float, float]]) -> float:
    """The time of the largest arm rotation speed (axis-angle change per frame) inside the given spans."""
    with np.load(report / "motion.npz") as motion:  # BEAT2 layout (gesture.process.write_motion)
        poses = motion["poses"].reshape(len(motion["poses"]), -1, 3)  # (T, 55, 3)
        fps = float(motion["mocap_frame_rate"])
    speed = np.linalg.norm(np.diff(poses[:, ARM_JOINTS], axis=0), axis=-1).sum(axis=1)  # (T-1,)
    times = (np.arange(len(speed)) + 1) / fps
    inside = np.zeros(len(speed), bool)
    for start, end in spans:
        inside |= (times >= start) & (times <= end)
    return float(times[np.argmax(np.where(inside, speed, -1.0))])


def save_frames(mp4: Path, at_s: dict[str, float], out: Path) -> None:
    with av.open(str(mp4)) as container:
        stream = container.streams.video[0]
        frames = [(float(frame.time), frame.to_ndarray(format="rgb24")) for frame in container.decode(stream)]
    out.mkdir(parents=True, exist_ok=True)
    for name, t in at_s.items():
        _, image = min(frames, key=lambda f: abs(f[0] - t))
        Image.fromarray(image).save(out / f"demo_{name}.png")
        print(f"{out}/demo_{name}.png: {t:.2f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mp4", type=Path, default=Path("out/demo.mp4"))
    parser.add_argument("--report", type=Path, default=Path("out/demo-report"))
    parser.add_argument("--out", type=Path, default=Path("docs"))
    args = parser.parse_args()
    user, agent = turns(args.report, "user"), turns(args.report, "agent")
    save_frames(
        args.mp4,
        {
            "listening": sum(user[0]) / 2,
            "answering": agent[0][0] + 0.5,
            "gesturing": fastest_arm_moment_s(args.report, agent),
        },
        args.out,
    )


if __name__ == "__main__":
    main()
