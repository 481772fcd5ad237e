"""The agent's voice on the picture's clock (dashboard.js: DisplayClock, VoiceScheduler, dueChunks), in the real
page in headless Chromium: driven on a simulated timeline (no real time passes), with the page's own avatar
playout (avatar.js: Playout, StepTracker) showing the steps; then the real AudioContext silenced by Stop."""

from __future__ import annotations

import asyncio
import json

from tests.test_browser_avatar import _in_a_page, needs_browser

# Steps of 80 ms: the voice's chunk of a step arrives VOICE(step, r) ms after the step's place on the 80 ms clock,
# its motion MOTION(step, r) ms after it (the gesture stage follows the dialogue's); the page draws every
# INTERVAL(r) ms. The agent speaks in SPEECH ([first, end) steps). The audio clock: a sample at audio time t is
# heard at page time 1000 t + OUTPUT_MS, and its now is the page's now. Each step shown gets the offset of its
# voice (ms; > 0: the voice after the picture).
VOICE_SIM = """(async () => {
  const m = await import('/static/avatar.js'), d = window.dashboard;
  const rng = ((seed) => () => (seed = (seed * 16807) % 2147483647) / 2147483647)(11);
  const voiceMs = VOICE, motionMs = MOTION, intervalMs = INTERVAL, steps = STEPS, speech = SPEECH;
  const OUTPUT_MS = 42, SAMPLES = 1920;
  const speaking = (s) => speech.some(([a, b]) => s >= a && s < b);
  const playout = new m.Playout(), tracker = new m.StepTracker();
  const display = new d.DisplayClock(), scheduler = new d.VoiceScheduler();
  const events = [];  // [time, kind, step], in time order; each source in order (a bus never reorders)
  let lastVoice = 0, lastMotion = 0;
  for (let s = 0; s < steps; s++) {
    lastVoice = Math.max(lastVoice, 80 * s + voiceMs(s, rng));
    lastMotion = Math.max(lastMotion, 80 * s + motionMs(s, rng));
    if (speaking(s)) events.push([lastVoice, "voice", s]);
    events.push([lastMotion, "motion", s]);
  }
  events.sort((a, b) => a[0] - b[0]);
  const pending = new Map(), received = new Set(), played = [], offsets = [], notShown = [];
  const audioTimeAt = (ms) => (ms - OUTPUT_MS) / 1000;
  let next = 0, nextDraw = 0;
  for (let now = 0; now < 80 * steps + 3000; now += 5) {
    while (next < events.length && events[next][0] <= now) {
      const [t, kind, s] = events[next++];
      if (kind === "voice") pending.set(s, new Int16Array(SAMPLES));
      else { playout.arrive(2 * s, 2, t); received.add(2 * s); received.add(2 * s + 1); }
    }
    for (const c of d.dueChunks(pending, scheduler, (s) => display.at(s), audioTimeAt, now / 1000)) {
      played.push({step: c.step, placed: c.placed});
    }
    if (now < nextDraw) continue;
    nextDraw = now + intervalMs(rng);
    const pos = playout.advance(now);
    if (pos === null) continue;
    for (const {step, shown} of tracker.drawn(pos, (f) => received.has(f))) {
      if (!shown) { notShown.push(step); continue; }
      display.shown(step, now);
      const chunk = played.find((p) => p.step === step && p.placed);
      if (chunk) offsets.push(1000 * (chunk.placed.at - chunk.placed.offsetS) + OUTPUT_MS - now);
    }
  }
  // the voice is continuous where a chunk abuts the one before it: it starts where that one ended
  let abut = 0, broken = 0;
  for (let i = 1; i < played.length; i++) {
    const [a, b] = [played[i - 1], played[i]];
    if (!b.placed || !b.placed.abuts) continue;
    if (a.placed && b.step === a.step + 1 && b.placed.at === a.placed.end) abut += 1; else broken += 1;
  }
  const sorted = [...offsets].sort((a, b) => a - b);
  const q = (p) => Math.round(sorted[Math.min(sorted.length - 1, Math.floor(p * sorted.length))]);
  return {chunks: played.length, skipped: played.filter((p) => !p.placed).map((p) => p.step), abut, broken,
          stats: scheduler.stats, offsets: offsets.length, p5: q(0.05), p50: q(0.5), p95: q(0.95),
          min: q(0), max: q(1), notShown: notShown.length};
})()"""
SPEECH = "[[10, 260], [300, 600]]"
JITTER = "(s, r) => 40 + 30 * r() + (s % 50 === 7 ? 60 : 0)"  # as test_browser_avatar's: a late step each 4 s
SIMULATIONS = {
    # the voice arrives 10-40 ms before the motion; drawn at 30 and 20 fps (+-30 %)
    **{
        f"{fps} fps": ("(s, r) => 10 + 20 * r()", JITTER, f"(r) => {1000 / fps:.3f} * (0.7 + 0.6 * r())")
        for fps in (30, 20)
    },
    # the voice arrives late now and then (150 ms after its place each 5 s): that chunk starts part-way or is
    # skipped; the ones after it are on time again
    "late voice": ("(s, r) => 10 + 20 * r() + (s % 62 === 30 ? 150 : 0)", JITTER, "(r) => 33"),
}


def _simulate(name: str) -> str:
    voice, motion, interval = SIMULATIONS[name]
    return (
        VOICE_SIM.replace("VOICE,", voice + ",")
        .replace("MOTION,", motion + ",")
        .replace("INTERVAL,", interval + ",")
        .replace("STEPS,", "600,")
        .replace("SPEECH;", SPEECH + ";")
    )


@needs_browser
def test_the_voice_is_heard_when_its_step_is_shown_and_stays_continuous():
    sims = dict(zip(SIMULATIONS, asyncio.run(_in_a_page([_simulate(name) for name in SIMULATIONS]))))
    print(json.dumps(sims))
    speech_steps = 250 + 300
    for fps in (30, 20):
        sim = sims[f"{fps} fps"]
        assert sim["chunks"] == speech_steps and sim["skipped"] == [] and sim["notShown"] == 0, sim
        # heard with its picture: within lip-sync's window (45 ms early, 125 ms late) by far, at 0 in the middle
        assert -20 <= sim["p5"] and sim["p95"] <= 45 and -15 <= sim["p50"] <= 25, sim
        # continuous: every chunk but the first of each utterance and a few re-syncs abuts the one before it
        assert sim["broken"] == 0 and sim["abut"] >= speech_steps - 2 - 10, sim
        assert sim["stats"]["spliced"] <= 2 + 10, sim
    late = sims["late voice"]
    # a late chunk is placed where its picture is (its start dropped) or skipped, never delaying the ones after it
    assert late["chunks"] == speech_steps and late["broken"] == 0, late
    assert len(late["skipped"]) <= 10 and late["stats"]["spliced"] >= 9, late
    assert -20 <= late["p5"] and late["p95"] <= 45, late


# The real AudioContext: the page learns that step s is shown at t0 + 80 s, gets a 220 Hz voice for steps 5-24 and
# schedules it ahead by itself; then the run is stopped. Every chunk scheduled ends (stopped) before its planned end
# on the audio clock, and nothing more is scheduled.
STOP_SCRIPT = """(async () => {
  const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
  ensureAudio();
  while (audio.ctx.state !== 'running' || !audio.ctx.getOutputTimestamp().performanceTime) await sleep(20);
  const t0 = performance.now();
  for (let s = 0; s < 5; s++) audio.display.shown(s, t0 - 80 * (5 - s));  // step 5 is shown at t0
  for (let s = 5; s < 25; s++) {
    const pcm = new Int16Array(1920).map((_, i) => 8000 * Math.sin(2 * Math.PI * 220 * (1920 * s + i) / 24000));
    onAudio(s, pcm);
  }
  while (dash.audioSteps < 4) await sleep(10);
  const ends = [];
  const planned = [...audio.sources].map((src) => {
    const item = {planned: audio.last && audio.last.src === src ? audio.last.end : null, ended: null};
    src.addEventListener('ended', () => { item.ended = audio.ctx.currentTime; });
    ends.push(item);
    return item;
  });
  const last = audio.last.end, stoppedAt = audio.ctx.currentTime, scheduled = dash.audioSteps;
  onRun({type: 'run', phase: 'stopped', wait_for_start: false, stages: {}});
  while (ends.some((e) => e.ended === null)) await sleep(10);
  await sleep(200);
  return {scheduled, after: dash.audioSteps, playing: planned.length, pending: audio.pending.size,
          sources: audio.sources.size, lastPlannedEnd: last, lastEnded: Math.max(...ends.map((e) => e.ended)),
          stoppedAt, voice: dash.voice};
})()"""


@needs_browser
def test_stop_silences_the_voice_scheduled_ahead():
    (result,) = asyncio.run(_in_a_page([STOP_SCRIPT]))
    print(json.dumps(result))
    assert result["scheduled"] >= 4 and result["playing"] >= 1, result
    assert result["after"] == result["scheduled"] and result["pending"] == 0 and result["sources"] == 0, result
    assert result["lastEnded"] < result["lastPlannedEnd"], result  # cut short, not played out
