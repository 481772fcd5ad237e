"""Issue 46, case 8: an hour-long offline run of the default agent; each stage's memory is flat after warm-up.

The user's side is the bundled recording (7.1 s) followed by 8 s of silence for the agent's answer, over and
over, for `ECAS_SOAK_S` seconds of audio (default 3600). Every `SAMPLE_S` the test reads each stage's resident
memory (VmRSS); the curve is written to `<report>/memory.json` (docs/soak.md shows one). After the warm-up (the
first `WARM_UP_SHARE` of the run), the median of the last quarter of the samples may exceed that of the
quarter after warm-up by `FLAT_MB` at most; the supervisor's too. Run it alone: `nice -n 10 python -m pytest -m slow
tests/test_trust_soak.py` (an hour of audio takes 1-2 h of wall time on a loaded 2-core machine).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from ecas.core.paths import EXAMPLES_DIR
from tests.test_reliability_runtime import stage_pid
from tests.test_runtime import leftovers

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = EXAMPLES_DIR / "librivox_0870.wav"
SOAK_S = float(os.environ.get("ECAS_SOAK_S", 3600))
ANSWER_PAUSE_S = 8.0
SAMPLE_S = 10.0
WARM_UP_SHARE = 0.25
FLAT_MB = 25.0  # the issue measured +37 MB in 120 s in the dialogue stage
STAGES = ("io", "dialogue", "gesture", "render")


def conversation(path: Path, seconds: float) -> Path:
    """The example and a pause, repeated to `seconds`, written block by block (16 kHz PCM16)."""
    speech, rate = sf.read(EXAMPLE, dtype="float32")
    cycle = np.concatenate([speech, np.zeros(int(ANSWER_PAUSE_S * rate), np.float32)])
    with sf.SoundFile(path, "w", rate, 1, "PCM_16") as f:
        for _ in range(int(np.ceil(seconds * rate / len(cycle)))):
            f.write(cycle)
    return path


def rss_mb(pid: int | None) -> float | None:
    if pid is None:
        return None
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def flatness(samples: list[dict], stage: str) -> tuple[float, float]:
    """(median MB of the quarter after warm-up, median MB of the last quarter) of one stage's curve."""
    values = [s[stage] for s in samples if s.get(stage) is not None]
    after = values[int(len(values) * WARM_UP_SHARE) :]
    quarter = max(1, len(after) // 4)
    return float(np.median(after[:quarter])), float(np.median(after[-quarter:]))


@pytest.mark.slow
@pytest.mark.timeout(0)  # it waits for the run's end itself (an hour of audio); no per-test limit
def test_an_hour_offline_keeps_every_stage_flat(tmp_path):
    wav = conversation(tmp_path / "conversation.wav", SOAK_S)
    report = Path(os.environ.get("ECAS_SOAK_REPORT", tmp_path / "run"))  # keep the curve: give a directory
    cmd = [sys.executable, str(ROOT / "launch.py"), "--replay", str(wav), "--headless", "--report", str(report)]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    console = (tmp_path / "console.log").open("w")  # read at the end: a pipe would fill and block the run
    proc = subprocess.Popen(
        [*cmd, "--set", "render.size=128"],
        cwd=ROOT,
        env=env,
        stdout=console,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    samples, t0, curve = [], time.monotonic(), tmp_path / "memory.json"
    while proc.poll() is None:
        pids = {stage: stage_pid(proc.pid, stage) for stage in STAGES}
        sample = {"t_s": round(time.monotonic() - t0, 1), "supervisor": rss_mb(proc.pid)}
        sample |= {stage: rss_mb(pid) for stage, pid in pids.items()}
        if any(sample[s] is not None for s in STAGES):
            samples.append(sample)
            curve.write_text(json.dumps({"audio_s": SOAK_S, "samples": samples}, indent=1))
        time.sleep(SAMPLE_S)
    code = proc.wait()
    console.close()
    output = (tmp_path / "console.log").read_text()
    (report / "memory.json").write_text(curve.read_text())
    assert code == 0, output[-3000:]
    assert len(samples) >= 8, samples
    for stage in ("supervisor", *STAGES):  # the launcher keeps every step's latency: 8 bytes a value
        start_mb, end_mb = flatness(samples, stage)
        assert end_mb - start_mb <= FLAT_MB, f"{stage}: {start_mb:.0f} MB -> {end_mb:.0f} MB after warm-up"
    assert leftovers(proc.pid) == []
