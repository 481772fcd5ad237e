"""The bundled demo through the real processes: every stage real, the MP4 checked as a viewer would."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.render_helpers import check_av_sync, decode, needs_osmesa, silhouette, silhouette_center

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def demo_runs(tmp_path_factory) -> dict:
    """The demo as `make demo` runs it ("a") and again with its default seed spelled out ("b"), side by side (an
    offline run must not depend on the machine's load) -> {run: (stdout, report dir, mp4)}."""
    root = tmp_path_factory.mktemp("demo")
    seeds = {"a": [], "b": ["--seed", "0"]}
    procs = {
        run: subprocess.Popen(
            [
                sys.executable,
                "launch.py",
                "--headless",
                *seed,
                "--mp4",
                str(root / f"{run}.mp4"),
                "--report",
                str(root / run),
                "--set",
                "render.size=160",
            ],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for run, seed in seeds.items()
    }
    runs = {}
    for run, proc in procs.items():
        output, _ = proc.communicate(timeout=600)
        assert proc.returncode == 0, output
        runs[run] = (output, root / run, root / f"{run}.mp4")
    return runs


@needs_osmesa
def test_demo_listens_answers_and_gestures(demo_runs):
    stdout, report, out = demo_runs["a"]
    # an offline run's table: throughput and compute, not queueing shown as end-to-end latency
    assert "x real time" in stdout and "frames/s" in stdout and "end to end" not in stdout

    latency = json.loads((report / "latency.json").read_text())
    n_steps = latency["steps_measured"]
    assert n_steps > 150 and set(latency["stages"]) == {"io", "dialogue", "gesture", "render"}
    assert all(c.get("dropped", 0) == 0 and c.get("lost", 0) == 0 for c in latency["counters"].values())

    turns = json.loads((report / "transcript.json").read_text())["turns"]
    user = " ".join(t["text"] for t in turns if t["speaker"] == "user")
    agent = [t for t in turns if t["speaker"] == "agent"]
    assert {"john", "dashwood"} & set(user.split())  # the real recording was understood
    assert agent and agent[0]["start_s"] > 6.0 and agent[0]["words"]  # the agent answered after the user

    info = decode(out)
    check_av_sync(info, 2 * n_steps)
    frames = info["frames"]
    for frame in frames[::25]:
        mask = silhouette(frame, ground_rows=0.15)
        assert mask.mean() > 0.02
        cx, _ = silhouette_center(mask)
        assert abs(cx - 0.5) < 0.15
    motion = [np.abs(a.astype(int) - b.astype(int)).mean() for a, b in zip(frames[:-12:12], frames[12::12])]
    assert np.median(motion) > 0.05  # the avatar keeps moving
    agent_start = int(agent[0]["start_s"] * 25)
    audio = info["audio"].mean(axis=0)
    assert np.abs(audio[agent_start * 960 : (agent_start + 50) * 960]).max() > 0.05  # the answer is heard


@needs_osmesa
def test_offline_runs_are_identical_with_the_same_seed(demo_runs):
    """The whole loop, real stages: same recording and seed → the same conversation, the same generated motion
    (every step's tokens and SMPL-X parameters, bit for bit) and the same MP4, pixel for pixel and sample for
    sample (pyrender's light order once followed object addresses: see render.renderer._stable_node_type)."""
    runs = []
    for _, report, mp4 in demo_runs.values():
        with np.load(report / "motion.npz") as motion:
            arrays = {k: motion[k] for k in motion.files}
        runs.append((arrays, (report / "transcript.json").read_text(), decode(mp4)))
    (motion_a, transcript_a, video_a), (motion_b, transcript_b, video_b) = runs
    assert transcript_a == transcript_b
    assert motion_a.keys() == motion_b.keys() and len(motion_a["tokens"]) > 100
    for key in motion_a:
        assert np.array_equal(motion_a[key], motion_b[key], equal_nan=True), key
    assert len(video_a["frames"]) == len(video_b["frames"]) == 2 * len(motion_a["tokens"])
    assert np.array_equal(video_a["audio"], video_b["audio"])
    assert all(np.array_equal(a, b) for a, b in zip(video_a["frames"], video_b["frames"]))


def test_speak_mode_makes_the_agent_say_a_recording(tmp_path):
    """`--speak`: the playback backend speaks the file with its transcript; the user side is silence."""
    proc = subprocess.run(
        [
            sys.executable,
            "launch.py",
            "--speak",
            "ecas/examples/librivox_0870.wav",
            "--headless",
            "--report",
            str(tmp_path),
            "--set",
            "dialogue.playback.transcript=ecas/examples/librivox_0870.txt",
            "--set",
            "run.components.render=tests.components:recorder",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    turns = json.loads((tmp_path / "transcript.json").read_text())["turns"]
    agent_words = [w["word"].lower() for t in turns if t["speaker"] == "agent" for w in t["words"]]
    assert "dashwood" in agent_words and not [t for t in turns if t["speaker"] == "user"]
    steps = [
        json.loads(line)["step"]
        for line in (tmp_path / "received.jsonl").read_text().splitlines()
        if json.loads(line)["topic"] == "gesture.step"
    ]
    assert steps == list(range(len(steps))) and len(steps) * 0.08 > 7.1  # the whole recording was gestured
