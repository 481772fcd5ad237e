"""VRM rigs in the page through @pixiv/three-vrm (static/vrm.js), in real headless Chromium (software WebGL,
loopback only): the VRM 0.x and 1.0 rigs `ecas rig` builds load through its VRMLoaderPlugin, their expression
manager takes the ARKit weights as render.rig.vrm_expression_weights says, the eyes look at the camera, the 1.0
rig's MToon material and spring bone chain work, and with the shipped agent speaking they move and make faces."""

from __future__ import annotations

import asyncio
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.dashboard.browser import HeadlessChromium, find_chromium
from agent.dashboard.vendor import missing
from ecas.core.paths import EXAMPLES_DIR
from render.arkit import ARKIT_INDEX
from render.rig import load_rig, retarget, vrm_expression_weights
from render.rig_build import build_rig_glb
from tests.test_dashboard import _drive_page, _press_stop

ROOT = Path(__file__).resolve().parents[1]
needs_browser = pytest.mark.skipif(
    find_chromium() is None or bool(missing()), reason="needs Chromium and the page's JavaScript (`npm ci`)"
)
STATE = """(() => {
  const a = window.ecasAvatar, v = a.player && a.player.vrm;
  return {ready: a.ready, error: a.error, kind: a.kind, fps: a.fps, draws: a.draws, shownStep: a.shownStep,
          errors: a.errors, lastError: a.lastError, vrm: v ? v.state() : null};
})()"""
# The head turns to and fro for 40 poses 30 ms apart: the spring chain must swing in the head's frame.
SWING = """(async () => {
  const p = window.ecasAvatar.player, out = [];
  for (let i = 0; i < 40; i++) {
    const poses = new Array(165).fill(0);
    poses[3 * 15 + 1] = 0.8 * Math.sin(i / 4);  // the head (joint 15) about y
    poses[3 * 12 + 0] = 0.4 * Math.sin(i / 3);  // the neck (joint 12) about x
    p.poseForTest(poses, [0, 1.3, 0], new Array(52).fill(0));
    out.push(p.vrm.state().springs);
    await new Promise((r) => setTimeout(r, 30));
  }
  return out;
})()"""


def _rig(tmp_path: Path, kind: str) -> Path:
    path = tmp_path / f"{kind}.vrm"
    path.write_bytes(build_rig_glb(kind))
    return path


async def _static_page(avatar: Path, script) -> dict:
    """The dashboard's server alone (no run) drawing `avatar`; `script(page)`'s result."""
    from agent.dashboard.events import hello_event
    from agent.dashboard.server import Hub, make_app, start_server

    def snapshot():
        return [hello_event(("io",), True, "s", False, render_mode="browser")]

    runner, port = await start_server(make_app(Hub(snapshot, lambda _c: None), avatar=str(avatar)), "127.0.0.1", 0)
    try:
        async with HeadlessChromium(f"http://127.0.0.1:{port}/", 800, 600) as page:
            await page.wait_for("window.ecasAvatar && (window.ecasAvatar.ready || window.ecasAvatar.error)", 120)
            await page.wait_for("window.ecasAvatar.draws > 2 || window.ecasAvatar.error", 60)
            return await script(page)
    finally:
        await runner.cleanup()


@needs_browser
@pytest.mark.parametrize("kind", ("vrm1", "vrm0"))
def test_a_vrm_loads_through_three_vrm_with_its_face_eyes_and_springs(tmp_path, kind):
    rig = _rig(tmp_path, kind)
    rng = np.random.default_rng(11)
    poses, trans = rng.normal(0, 0.3, (55, 3)), np.array([0.05, 1.28, 0.1])
    weights = np.zeros(52)
    for name, value in (("eyeBlinkLeft", 0.9), ("eyeBlinkRight", 0.4), ("jawOpen", 0.35), ("mouthSmileLeft", 0.5)):
        weights[ARKIT_INDEX[name]] = value
    weights[ARKIT_INDEX["mouthSmileRight"]] = 0.5
    weights[ARKIT_INDEX["mouthLowerDownLeft"]] = weights[ARKIT_INDEX["mouthLowerDownRight"]] = 0.6
    weights[ARKIT_INDEX["mouthPucker"]] = 0.3
    args = json.dumps([poses.ravel().tolist(), trans.tolist(), weights.tolist()])

    async def script(page):
        loaded = await page.evaluate(STATE)
        positions = await page.evaluate(f"window.ecasAvatar.player.poseForTest(...{args})")
        posed = await page.evaluate(STATE)
        swing = await page.evaluate(SWING) if kind == "vrm1" else []
        rest = json.dumps([[0.0] * 165, [0.0, 1.3, 0.0], [0.0] * 52])
        await page.evaluate(f"window.ecasAvatar.player.poseForTest(...{rest})")
        await asyncio.sleep(1.5)  # the camera settles in front of the rig (it follows the pelvis, 0.4 s)
        await page.evaluate(f"window.ecasAvatar.player.poseForTest(...{rest})")
        upright = await page.evaluate(STATE)
        return loaded, positions, posed, swing, upright

    loaded, positions, posed, swing, upright = asyncio.run(_static_page(rig, script))
    assert loaded["ready"] and not loaded["error"] and loaded["kind"] == kind, loaded
    assert loaded["vrm"]["meta"] == ("1" if kind == "vrm1" else "0")  # three-vrm read the file's VRM extension
    # the humanoid, driven through the normalized bones, lands where the numpy retargeting puts it
    expected = retarget(load_rig(rig), poses, trans)
    errors = [np.linalg.norm(np.array(p) - expected[int(n)][:3, 3]) for n, p in positions.items()]
    assert len(errors) == 55 and max(errors) < 1e-4, max(errors)
    # the face: the expression manager holds what render.rig says for every expression the file defines
    reference = vrm_expression_weights(weights)
    values = posed["vrm"]["expressions"]
    assert set(values) == {"happy", "blink", "aa", "ih", "ou", "ee", "surprised"}  # the rig's presets
    for name, value in values.items():
        assert value == pytest.approx(reference[name], abs=1e-6), name
    assert values["blink"] == pytest.approx(0.4) and values["aa"] == pytest.approx(0.35)
    # upright, the eyes look at the camera, which stands in front of the rig at its pelvis's height: down
    look = upright["vrm"]["lookAt"]
    assert look is not None and abs(look["yaw"]) < 5 and look["pitch"] > 2, look  # three-vrm: pitch > 0 is down
    assert upright["vrm"]["eyeTurnDeg"] > 0.5  # the bone applier turned the eye (90° in -> 10° out by default)
    if kind == "vrm1":
        assert posed["vrm"]["materials"] == ["MToonMaterial"]
        tips = [state[-1]["inHead"] for state in swing]  # the chain's last simulated joint, in the head's frame
        assert all(math.isfinite(c) for tip in tips for c in tip)
        spread = np.ptp(np.array(tips), axis=0)
        assert spread.max() > 0.005, spread  # it swings behind the turning head (a rigid child would not)
        assert max(np.linalg.norm(t) for t in tips) < 0.3  # and stays on its 0.2 m chain
    else:
        assert posed["vrm"]["springs"] == []
    print(json.dumps({"kind": kind, "max_error_m": max(errors), "lookAt": look}))


@needs_browser
@pytest.mark.parametrize("kind", ("vrm1", "vrm0"))
def test_a_vrm_moves_and_makes_faces_with_the_speaking_agent(tmp_path, kind):
    """The shipped agent speaks the packaged example (`--speak`): the VRM's bones follow the stream and its
    expression manager's values change with the agent's face; no page error, spring bones included."""
    rig = _rig(tmp_path, kind)
    report = tmp_path / "run"
    cmd = [sys.executable, str(ROOT / "launch.py"), "--speak", str(EXAMPLES_DIR / "librivox_0870.wav")]
    cmd += ["--avatar", str(rig), "--set", "dashboard.port=0", "--set", "dashboard.wait_for_start=true"]
    cmd += ["--report", str(report)]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    samples, code, output = _drive_page(proc, report, _watch, finish_timeout_s=180, url_timeout_s=300)
    assert code == 0, output[-3000:]
    rest, playing = samples[0], samples[1:]
    assert rest["ready"] and not rest["error"] and rest["kind"] == kind
    assert all(s["errors"] == 0 and not s["lastError"] for s in samples), samples[-1]
    assert playing[-1]["shownStep"] > playing[0]["shownStep"] >= 5
    faces = {json.dumps({k: round(v, 3) for k, v in s["vrm"]["expressions"].items()}) for s in playing}
    assert len(faces) >= 3, faces  # the expressions change with the agent's face
    moved = {name for s in playing for name, v in s["vrm"]["expressions"].items() if v > 0.02}
    assert moved & {"aa", "ih", "ou", "ee"} and moved & {"blink", "happy", "surprised"}, moved
    if kind == "vrm1":
        tips = np.array([s["vrm"]["springs"][-1]["inHead"] for s in playing])
        assert np.isfinite(tips).all() and np.ptp(tips, axis=0).max() > 1e-4
    fps = [s["fps"] for s in playing]
    print(json.dumps({"kind": kind, "fps_median": float(np.median(fps)), "fps": fps, "moved": sorted(moved)}))


async def _watch(url: str) -> list[dict]:
    async with HeadlessChromium(url, 1280, 1000) as page:
        await page.wait_for("window.ecasAvatar && window.ecasAvatar.ready && window.ecasAvatar.draws > 2", 120)
        await page.wait_for("window.dashboard.phase === 'ready'", timeout_s=120)
        samples = [await page.evaluate(STATE)]
        await page.evaluate("document.getElementById('start').click()")
        await page.wait_for("window.ecasAvatar.shownStep >= 5", timeout_s=120)
        for _ in range(16):  # about 5 s of the 7 s the agent speaks
            samples.append(await page.evaluate(STATE))
            await asyncio.sleep(0.3)
        await _press_stop(page)
        return samples
