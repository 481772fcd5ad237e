"""The bundled demo through the real processes: every stage real, the MP4 checked as a viewer would."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from render.testing import check_av_sync, decode, needs_osmesa, silhouette, silhouette_center

ROOT = Path(__file__).resolve().parents[1]


@needs_osmesa
def test_demo_listens_answers_and_gestures(tmp_path):
    out = tmp_path / "demo.mp4"
    proc = subprocess.run([sys.executable, "launch.py", "--headless", "--mp4", str(out), "--report", str(tmp_path),
                           "--set", "render.size=160"], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    # an offline run's table: throughput and compute, not queueing shown as end-to-end latency
    assert "x real time" in proc.stdout and "frames/s" in proc.stdout and "end to end" not in proc.stdout

    latency = json.loads((tmp_path / "latency.json").read_text())
    n_steps = latency["steps_measured"]
    assert n_steps > 150 and set(latency["stages"]) == {"io", "dialogue", "gesture", "render"}
    assert all(c.get("dropped", 0) == 0 and c.get("lost", 0) == 0 for c in latency["counters"].values())

    turns = json.loads((tmp_path / "transcript.json").read_text())["turns"]
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
    assert np.abs(audio[agent_start * 960:(agent_start + 50) * 960]).max() > 0.05  # the answer is heard


@needs_osmesa
def test_offline_runs_are_identical_with_the_same_seed(tmp_path):
    """The whole loop, real stages: same recording and seed → the same conversation, the same generated motion
    (every step's tokens and SMPL-X parameters, bit for bit) and the same MP4, pixel for pixel and sample for
    sample (pyrender's light order once followed object addresses: see render.renderer._stable_node_type)."""
    procs = {run: subprocess.Popen([sys.executable, "launch.py", "--headless", "--seed", "3", "--mp4",
                                    str(tmp_path / f"{run}.mp4"), "--report", str(tmp_path / run), "--set",
                                    "render.size=96"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                   text=True)
             for run in ("a", "b")}  # side by side: an offline run must not depend on the machine's load
    runs = []
    for run, proc in procs.items():
        output, _ = proc.communicate(timeout=600)
        assert proc.returncode == 0, output
        with np.load(tmp_path / run / "motion.npz") as motion:
            arrays = {k: motion[k] for k in motion.files}
        runs.append((arrays, (tmp_path / run / "transcript.json").read_text(), decode(tmp_path / f"{run}.mp4")))
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
    proc = subprocess.run([sys.executable, "launch.py", "--speak", "assets/examples/librivox_0870.wav", "--headless",
                           "--report", str(tmp_path),
                           "--set", "dialogue.playback.transcript=assets/examples/librivox_0870.txt",
                           "--set", "run.components.render=tests.components:recorder"],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    turns = json.loads((tmp_path / "transcript.json").read_text())["turns"]
    agent_words = [w["word"].lower() for t in turns if t["speaker"] == "agent" for w in t["words"]]
    assert "dashwood" in agent_words and not [t for t in turns if t["speaker"] == "user"]
    steps = [json.loads(line)["step"] for line in (tmp_path / "received.jsonl").read_text().splitlines()
             if json.loads(line)["topic"] == "gesture.step"]
    assert steps == list(range(len(steps))) and len(steps) * 0.08 > 7.1  # the whole recording was gestured
