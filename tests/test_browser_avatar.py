"""render.mode browser: the server draws nothing for the dashboard, and the page draws the avatar with three.js
from the motion stream, in real headless Chromium (software WebGL, loopback only)."""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
import soundfile as sf

from agent.dashboard.browser import HeadlessChromium, find_chromium
from agent.dashboard.server import THREE_DIR
from agent.latency import DISPLAY_KEY, LatencyRecorder
from ecas.core.component import RunContext
from ecas.core.config import ConfigError
from ecas.core.messages import GestureStep, Metrics
from render.config import RenderConfig
from render.process import RenderComponent
from tests.test_dashboard import _drive_page, _press_stop
from tests.test_runtime import launch, leftovers

AVATAR_STATE = """(() => {
  const a = window.ecasAvatar, s = a.player ? a.player.sample() : {};
  return {fps: a.fps, draws: a.draws, received: a.received, shownStep: a.shownStep, ready: a.ready, error: a.error,
          kind: a.kind,
          different: s.different, checksum: s.checksum, pixels: s.pixels, audioSteps: window.dashboard.audioSteps,
          audioLastStep: window.dashboard.audioLastStep, displaySamples: window.dashboard.displaySamples,
          clockRttMs: window.dashboard.clockRttMs, videoHidden: document.getElementById('video').hidden,
          canvasShown: !document.getElementById('avatar').hidden};
})()"""


def test_render_mode_is_validated():
    assert RenderConfig().mode == "server"
    with pytest.raises(ConfigError, match="render.mode"):
        RenderConfig(mode="client")


def test_browser_mode_renders_no_frame_and_keeps_the_latency_stamps(tmp_path):
    component = RenderComponent(RenderConfig(mode="browser"), RunContext(tmp_path, live=True, seed=0, session="s"))
    assert component.view is None  # no GL context at all
    msg = GestureStep(
        poses=np.zeros((2, 55, 3), np.float32),
        trans=np.zeros((2, 3), np.float32),
        expressions=np.zeros((2, 100), np.float32),
        tokens=np.zeros(20, np.int32),
    )
    frames = component.handle(msg)
    assert [f.frame_index for f in frames] == [0, 1]
    assert all(f.encoding == "none" and f.image.size == 0 for f in frames)
    assert component.counters()["rendered_frames"] == 0
    component.close()


def test_display_samples_are_summarised_apart_from_the_sink_latency():
    recorder = LatencyRecorder(("io", "render"))
    for step in (3, 4, 6, 7):
        recorder.add(Metrics(step=step, values={DISPLAY_KEY: 100.0 + step, "clock_rtt_ms": 0.5}), {})
    recorder.add(Metrics(step=7, values={DISPLAY_KEY: 999.0, "clock_rtt_ms": 0.5}), {})  # a second page: ignored
    assert recorder.e2e_ms == []
    display = recorder.summary({}, {})["display"]
    assert display["steps_shown"] == 4 and display["steps_not_shown"] == 1  # step 5
    assert display["end_to_end_ms"]["max"] == 107.0 and display["clock_rtt_ms"]["p50"] == 0.5


needs_browser = pytest.mark.skipif(
    find_chromium() is None or not THREE_DIR.is_dir(),
    reason="needs Chromium (scripts/install_system.sh) and three.js (`npm ci`)",
)


@needs_browser
def test_the_page_draws_the_avatar_moving_with_the_stream_and_the_voice(tmp_path):
    wav = tmp_path / "talk.wav"
    t = np.arange(16000 * 30) / 16000
    sf.write(wav, (0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32), 16000)
    report = tmp_path / "run"
    args = ["--replay", str(wav), "--set", "render.mode=browser", "--set", "dashboard.wait_for_start=true"]
    proc = launch(args, report)
    (rest, early, later), code, output = _drive_page(proc, report, _watch, finish_timeout_s=120, url_timeout_s=300)
    assert code == 0, output
    assert leftovers(proc.pid) == []
    assert rest["ready"] and not rest["error"] and rest["videoHidden"] and rest["canvasShown"]
    assert rest["different"] > 0.02 * rest["pixels"]  # the avatar in its rest pose covers the canvas
    for state in (early, later):
        assert state["different"] > 0.02 * state["pixels"] and state["fps"] > 0
    # tests.components.WaveGesture swings the right arm with the step: the image changes as the motion does
    assert len({rest["checksum"], early["checksum"], later["checksum"]}) == 3
    assert later["shownStep"] > early["shownStep"] >= 10 and later["received"] > early["received"]
    # the voice follows the avatar: each step's audio is played as the step is shown
    assert later["audioSteps"] > 0 and abs(later["audioLastStep"] - later["shownStep"]) <= 3
    # latency to the display: the page reported the steps it showed; the run's latency.json has them
    assert later["displaySamples"] > 0 and 0 <= later["clockRttMs"] < 1000
    display = json.loads((report / "latency.json").read_text())["display"]
    span = display["steps_shown"] + display["steps_not_shown"]  # a page drawing < 12.5 fps skips steps
    assert display["steps_shown"] >= 10 and span >= later["shownStep"] - early["shownStep"]
    assert 0 < display["end_to_end_ms"]["p50"] < 10_000
    print(json.dumps({"fps": later["fps"], "draws": later["draws"], "display": display}))


async def _watch(url: str) -> tuple[dict, dict, dict]:
    async with HeadlessChromium(url, 1280, 1000) as page:
        await page.wait_for("window.ecasAvatar && window.ecasAvatar.ready && window.ecasAvatar.draws > 2", 90)
        await page.wait_for("window.dashboard.phase === 'ready'", timeout_s=90)
        rest = await page.evaluate(AVATAR_STATE)
        await page.evaluate("document.getElementById('start').click()")
        await page.wait_for("window.ecasAvatar.shownStep >= 10", timeout_s=60)
        early = await page.evaluate(AVATAR_STATE)
        await page.wait_for(f"window.ecasAvatar.shownStep >= {early['shownStep'] + 15}", timeout_s=60)
        await asyncio.sleep(0.1)
        later = await page.evaluate(AVATAR_STATE)
        await _press_stop(page)
        return rest, early, later


@needs_browser
@pytest.mark.parametrize("kind", ("vrm0", "mixamo"))
def test_a_users_rig_loads_and_moves_in_the_page(tmp_path, kind):
    """launch.py --avatar FILE with a VRM 0.x (facing -z) or a Mixamo-style rig (A-pose, scaled armature) the
    project builds: the page draws it, its bones follow the stream."""
    from render.rig_build import build_rig_glb

    rig = tmp_path / f"rig.{'vrm' if kind == 'vrm0' else 'glb'}"
    rig.write_bytes(build_rig_glb(kind))
    wav = tmp_path / "talk.wav"
    t = np.arange(16000 * 20) / 16000
    sf.write(wav, (0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32), 16000)
    report = tmp_path / "run"
    args = ["--replay", str(wav), "--avatar", str(rig), "--set", "dashboard.wait_for_start=true"]
    proc = launch(args, report)
    (rest, early, later), code, output = _drive_page(proc, report, _watch, finish_timeout_s=120, url_timeout_s=300)
    assert code == 0, output
    assert rest["ready"] and not rest["error"] and rest["kind"] == kind
    for state in (rest, early, later):
        assert state["different"] > 0.02 * state["pixels"]
    assert len({rest["checksum"], early["checksum"], later["checksum"]}) == 3
    assert later["shownStep"] > early["shownStep"] and later["fps"] > 0


async def _page_poses(avatar: str | None, poses: np.ndarray, trans: np.ndarray) -> dict:
    """The dashboard's server alone (no run) with `avatar`; the page poses one frame with its three.js code and
    returns each driven node's world position."""
    from agent.dashboard.events import hello_event
    from agent.dashboard.server import Hub, make_app, start_server

    def snapshot():
        return [hello_event(("io",), True, "s", False, render_mode="browser")]

    runner, port = await start_server(make_app(Hub(snapshot, lambda _c: None), avatar=avatar), "127.0.0.1", 0)
    try:
        async with HeadlessChromium(f"http://127.0.0.1:{port}/", 800, 600) as page:
            await page.wait_for("window.ecasAvatar && window.ecasAvatar.ready", timeout_s=120)
            args = json.dumps([poses.ravel().tolist(), trans.tolist(), [0.0] * 52])
            return await page.evaluate(f"window.ecasAvatar.player.poseForTest(...{args})")
    finally:
        await runner.cleanup()


@needs_browser
def test_the_pages_three_js_retargeting_equals_the_numpy_reference(tmp_path):
    """Same pose, four avatars (ours, VRM 1.0, VRM 0.x, Mixamo-style): the bones' world positions in the page
    equal render.rig.retarget's."""
    from render.rig import load_rig, retarget
    from render.rig_build import build_rig_glb

    rng = np.random.default_rng(5)
    poses, trans = rng.normal(0, 0.4, (55, 3)), np.array([0.1, 1.25, 0.2])
    for kind in ("ours", "vrm1", "vrm0", "mixamo"):
        path = None
        if kind != "ours":
            path = tmp_path / f"{kind}.glb"
            path.write_bytes(build_rig_glb(kind))
        positions = asyncio.run(_page_poses(str(path) if path else None, poses, trans))
        if path is None:
            from agent.dashboard.avatar_file import cached_avatar_glb

            path = cached_avatar_glb()
        expected = retarget(load_rig(path), poses, trans)
        errors = [np.linalg.norm(np.array(p) - expected[int(n)][:3, 3]) for n, p in positions.items()]
        assert len(errors) >= 54 and max(errors) < 1e-4, (kind, max(errors))


def test_browser_mode_without_an_mp4_runs_no_render_stage():
    from agent.sections import load_app_config
    from ecas.core.paths import DEFAULT_CONFIG
    from ecas.launch import without_relaying_renderer

    def stages(*overrides):
        return without_relaying_renderer(load_app_config(DEFAULT_CONFIG, list(overrides))).run.stages

    assert stages() == ("io", "dialogue", "gesture", "render")  # server mode draws the frames
    assert stages("render.mode=browser") == ("io", "dialogue", "gesture")  # the page draws them
    assert stages("render.mode=browser", "render.mp4_path=out.mp4") == ("io", "dialogue", "gesture", "render")


# The page's clock and step accounting (avatar.js's Playout and StepTracker) driven on a simulated timeline in the
# real page: steps of 2 frames produced every 80 ms arrive after ARRIVAL(step, random) ms and are drawn every
# INTERVAL(random) ms; MISSING steps never arrive. No real time passes.
PLAYOUT_SIM = """(async () => {
  const m = await import('/static/avatar.js');
  const rng = ((seed) => () => (seed = (seed * 16807) % 2147483647) / 2147483647)(7);
  const arrivalMs = ARRIVAL, intervalMs = INTERVAL, steps = STEPS, missing = new Set(MISSING);
  const playout = new m.Playout(), tracker = new m.StepTracker();
  const arrivals = [];
  let previous = 0;  // the bus delivers in order: a step never overtakes the one before it
  for (let s = 0; s < steps; s++) {
    previous = Math.max(previous, 80 * s + arrivalMs(s, rng));
    if (!missing.has(s)) arrivals.push([s, previous]);
  }
  const received = new Set(), reached = {}, shown = [], skipped = [];
  let next = 0;
  for (let now = 0; now < 80 * steps + 3000; now += intervalMs(rng)) {
    while (next < arrivals.length && arrivals[next][1] <= now) {
      const [s, t] = arrivals[next++];
      playout.arrive(2 * s, 2, t);
      received.add(2 * s); received.add(2 * s + 1);
    }
    const pos = playout.advance(now);
    if (pos === null) continue;
    for (const {step, shown: was} of tracker.drawn(pos, (f) => received.has(f))) {
      (was ? shown : skipped).push(step);
      reached[step] = now - 80 * step;  // drawn this long after the step's place on the 80 ms clock
    }
  }
  const display = Object.values(reached).sort((a, b) => a - b);
  const q = (p) => display[Math.min(display.length - 1, Math.floor(p * display.length))];
  return {shown: shown.length, skipped, p50: q(0.5), p95: q(0.95), max: q(1), stats: playout.stats};
})()"""
JITTER = "(s, r) => 40 + 30 * r() + (s % 50 === 7 ? 60 : 0)"  # 40-70 ms, and one step of 100-130 ms each 4 s
SIMULATIONS = {
    # drawn at 60, 30, 20 and 13 fps (each interval +-30 %): no step skipped, each drawn soon after it arrives
    **{f"{fps} fps": (JITTER, f"(r) => {1000 / fps:.3f} * (0.7 + 0.6 * r())", []) for fps in (60, 30, 20, 13)},
    # the pipeline stalls for 600 ms every 10 s, then its steps arrive at once: caught up, none skipped
    "stalls": ("(s, r) => 50 + 20 * r() + (s % 125 === 110 ? 600 : 0)", "(r) => 33", []),
    # a stall of 3 s: the playhead jumps, the steps it jumped over are counted as not shown
    "long stall": ("(s, r) => 50 + (s === 200 ? 3000 : 0)", "(r) => 33", []),
    # steps whose frames never arrived are not shown, whatever the playhead did
    "lost steps": (JITTER, "(r) => 33", [300, 301, 450]),
}


async def _in_a_page(scripts: list[str]) -> list:
    """Evaluate scripts in the dashboard's page (its server alone, no run)."""
    from agent.dashboard.events import hello_event
    from agent.dashboard.server import Hub, make_app, start_server

    def snapshot():
        return [hello_event(("io",), True, "s", False, render_mode="browser")]

    runner, port = await start_server(make_app(Hub(snapshot, lambda _c: None)), "127.0.0.1", 0)
    try:
        async with HeadlessChromium(f"http://127.0.0.1:{port}/", 800, 600) as page:
            await page.wait_for("window.ecasAvatar && window.ecasAvatar.ready", timeout_s=120)
            return [await page.evaluate(s) for s in scripts]
    finally:
        await runner.cleanup()


@needs_browser
def test_the_pages_playout_shows_every_step_soon_after_it_arrives():
    scripts = [
        PLAYOUT_SIM.replace("ARRIVAL", a).replace("INTERVAL", i).replace("STEPS", "600").replace("MISSING", str(m))
        for a, i, m in SIMULATIONS.values()
    ]
    sims = dict(zip(SIMULATIONS, asyncio.run(_in_a_page(scripts))))
    print(json.dumps(sims))
    for fps in (60, 30, 20, 13):
        sim = sims[f"{fps} fps"]
        assert sim["skipped"] == [] and sim["shown"] == 600 and sim["stats"]["jumps"] == 0, (fps, sim)
        # the delay follows the arrivals' 90 % quantile (about 67 ms) plus the margin: a step is drawn at the
        # first display tick after that (1.3 draw intervals at most)
        assert 60 <= sim["p50"] <= 72 + 1300 / fps and sim["p95"] <= 80 + 1300 / fps, (fps, sim)
    stalls = sims["stalls"]
    assert stalls["skipped"] == [] and stalls["shown"] == 600 and stalls["stats"]["holds"] >= 4, stalls
    assert stalls["p50"] < 120, stalls  # between the stalls the delay comes back near the arrivals'
    long_stall = sims["long stall"]
    assert long_stall["stats"]["jumps"] == 1 and 0 < len(long_stall["skipped"]) <= 38, long_stall  # of 38 late
    assert long_stall["shown"] + len(long_stall["skipped"]) == 600
    lost = sims["lost steps"]
    assert lost["skipped"] == [300, 301, 450] and lost["shown"] == 597, lost


CPU_DEFORM = """(() => {
  const player = window.ecasAvatar.player, items = player.deform.items, {mesh, geometry} = items[0];
  const morphs = [];
  for (const weights of WEIGHTS) {  // one set after another: each from the base, not from the last
    weights.forEach((w, i) => { mesh.morphTargetInfluences[i] = w; });
    player.deform.update();
    morphs.push({position: Array.from(items[0].source.position), normal: Array.from(items[0].source.normal)});
  }
  player.poseForTest(POSE, [0.1, 1.25, 0.2], new Array(52).fill(0));  // skins the mesh (and its morphs)
  const skinned = Array.from(geometry.attributes.position.array);
  const v = new mesh.position.constructor(), three = [];
  for (let i = 0; i < geometry.attributes.position.count; i += 7) {  // three.js's own CPU skinning
    v.fromArray(items[0].source.position, 3 * i);
    three.push([i, ...mesh.applyBoneTransform(i, v).toArray()]);
  }
  return {meshes: items.length, shaderMorphs: geometry.morphAttributes.position !== undefined,
          shaderSkin: mesh.isSkinnedMesh, targets: mesh.morphTargetInfluences.length, morphs, skinned, three};
})()"""


@needs_browser
def test_the_pages_cpu_morphs_and_skinning_equal_gltfs_and_three_js():
    """The page morphs and skins the avatar on the CPU (not in SwiftShader's vertex shader): the morphed positions
    and normals equal glTF's sum of weighted targets computed here from the file, and the skinned positions equal
    three.js's SkinnedMesh.applyBoneTransform (what its shader computes) for a random pose."""
    from agent.dashboard.avatar_file import cached_avatar_glb
    from render.gltf import read_glb

    rng = np.random.default_rng(3)
    weights = [rng.uniform(0, 1, 52) * (rng.uniform(size=52) < 0.5), np.zeros(52), rng.uniform(0, 1, 52)]
    pose = rng.normal(0, 0.4, 165)
    script = CPU_DEFORM.replace("WEIGHTS", json.dumps([w.tolist() for w in weights]))
    (result,) = asyncio.run(_in_a_page([script.replace("POSE", json.dumps(pose.tolist()))]))
    assert result["meshes"] == 1 and result["targets"] == 52
    assert not result["shaderMorphs"] and not result["shaderSkin"]
    gltf = read_glb(cached_avatar_glb().read_bytes())
    prim = gltf.doc["meshes"][0]["primitives"][0]
    for w, page in zip(weights, result["morphs"]):
        for attribute, key in (("POSITION", "position"), ("NORMAL", "normal")):
            expected = gltf.accessor(prim["attributes"][attribute]).astype(np.float64)
            for k, target in enumerate(prim["targets"]):
                if attribute in target:
                    expected = expected + w[k] * gltf.accessor(target[attribute])
            assert np.abs(np.reshape(page[key], (-1, 3)) - expected).max() < 1e-5, (attribute, w[:3])
    skinned = np.reshape(result["skinned"], (-1, 3))
    three = np.array(result["three"])
    assert len(three) > 1000 and np.ptp(skinned, axis=0).min() > 0.1  # posed, not collapsed
    assert np.abs(skinned[three[:, 0].astype(int)] - three[:, 1:]).max() < 1e-5
