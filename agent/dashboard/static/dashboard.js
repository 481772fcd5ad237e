// The dashboard page: one WebSocket; JSON events (text) and frames / agent audio (binary, 8-byte header:
// u8 kind, pad, u16 frame index, u32 step). No libraries, nothing fetched from elsewhere.
"use strict";

const STEP_S = 0.08;
const KIND_FRAME = 1, KIND_AUDIO = 2, KIND_MIC = 3, KIND_MOTION = 4;
const HISTORY = 250;  // steps on the charts (20 s)
const MAX_TURNS = 200;
const STAGE_COLORS = ["#8e9aaf", "#4c9be8", "#f0a13a", "#5cb85c", "#c678dd"];
const TURN_COLORS = {user: "#4c9be8", agent: "#5cb85c", overlap: "#e8a23c", none: "#2a323b"};

// Read by the tests and handy in the console.
const dash = window.dashboard = {
  frames: 0, framesSkipped: 0, lastFrameStep: -1, latencySamples: 0, chartDraws: 0, chartLastStep: -1, words: 0,
  phase: "connecting", pipeline: [], audioSteps: 0, micBlocks: 0, userDbfs: -90,
};

const $ = (id) => document.getElementById(id);
let ws = null;
let latency = [];          // recent latency events
let turnHistory = [];      // recent floor states
let chartDirty = false, stripDirty = false;
let waitForStart = false;

// ---- connection -----------------------------------------------------------------------------------------
function connect() {
  ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  ws.binaryType = "arraybuffer";
  ws.onopen = () => { $("connection").textContent = "connected"; $("connection").className = "conn up";
                      clock.probes = []; probeClock();
                      if (audio.ctx) send({type: "audio", enabled: true}); };  // motion: asked for in onHello
  ws.onclose = () => { $("connection").textContent = "offline"; $("connection").className = "conn";
                       setTimeout(connect, 1000); };
  ws.onmessage = (m) => (typeof m.data === "string" ? onEvent(JSON.parse(m.data)) : onBinary(m.data));
}

function send(obj) { if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(obj)); }

function onEvent(e) {
  switch (e.type) {
    case "hello": onHello(e); break;
    case "run": onRun(e); break;
    case "turn": onTurn(e); break;
    case "turn_removed": { const el = turnEls.get(e.id); if (el) el.remove(); turnEls.delete(e.id); break; }
    case "vad": onVad(e); break;
    case "latency": onLatency(e); break;
    case "counters": onCounters(e); break;
    case "mic": if (!e.granted) { stopMic(); $("micinfo").textContent = e.reason; } break;
    case "clock": onClock(e); break;
    case "display_latency": onDisplayLatency(e); break;
  }
}

function onBinary(buf) {
  const view = new DataView(buf);
  const kind = view.getUint8(0), index = view.getUint16(2, true), step = view.getUint32(4, true);
  if (kind === KIND_FRAME) onFrame(step, index, new Blob([new Uint8Array(buf, 8)], {type: "image/jpeg"}));
  else if (kind === KIND_AUDIO) onAudio(step, new Int16Array(buf, 8));
  else if (kind === KIND_MOTION && avatar.player) avatar.player.push(buf, 8);
}

// ---- run state and controls -----------------------------------------------------------------------------
function onHello(e) {
  dash.pipeline = e.pipeline;
  if (e.render_mode === "browser") startAvatar();
  $("mic").hidden = !e.browser_mic;
  if (mic.on) send({type: "mic", enabled: true});  // reconnected: claim the microphone again
  latency = []; turnHistory = []; chartDirty = stripDirty = true;
  turnEls.forEach((el) => el.remove()); turnEls.clear();
  $("legend").innerHTML = e.pipeline.map((s, i) => `<span><i style="background:${STAGE_COLORS[i]}"></i>${s}</span>`)
    .join("") + `<span><i style="background:#fff"></i>end to end</span>` +
    `<span><i style="background:#f5d442"></i>to this page's display</span>` + (e.live ? "" : "<span>(offline run)</span>");
  displayLatency = [];
}

function onRun(e) {
  dash.phase = e.phase;
  if (e.phase === "stopped") silenceVoice();
  waitForStart = e.wait_for_start;
  const label = {ready: waitForStart ? "ready: press Start" : "ready"}[e.phase] || e.phase;
  $("phase").textContent = label;
  $("phase").className = "badge " + e.phase;
  $("start").disabled = !(waitForStart && e.phase === "ready");
  $("stop").disabled = !["starting", "ready", "running"].includes(e.phase);
  renderStageStates(e.stages);
}

$("start").onclick = () => { send({type: "control", command: "start"}); $("start").disabled = true; ensureAudio(); };
$("stop").onclick = () => { send({type: "control", command: "stop"}); $("stop").disabled = true; silenceVoice(); };
$("sound").onchange = (ev) => {
  if (ev.target.checked) ensureAudio();
  send({type: "audio", enabled: ev.target.checked});
};

// ---- video ----------------------------------------------------------------------------------------------
// Frames are decoded in order and shown at the render rate: the render stage publishes a step's two frames
// together, so the second one waits a frame period. A backlog beyond a few frames is skipped to stay live.
const FRAME_MS = 1000 * STEP_S / 2;
const MAX_QUEUED_FRAMES = 4;
const frameQueue = [];  // [bitmap, step, index], decoded, oldest first
let decodes = Promise.resolve(), pendingDecodes = 0, lastShownMs = 0;

function onFrame(step, index, blob) {
  if (pendingDecodes >= MAX_QUEUED_FRAMES) { dash.framesSkipped += 1; return; }
  pendingDecodes += 1;
  decodes = decodes.then(() => createImageBitmap(blob)).then((bitmap) => {
    frameQueue.push([bitmap, step, index]);
    while (frameQueue.length > MAX_QUEUED_FRAMES) { frameQueue.shift()[0].close(); dash.framesSkipped += 1; }
  }).catch(() => {}).finally(() => { pendingDecodes -= 1; });
}

function showFrames() {
  const now = performance.now();
  if (!frameQueue.length || (now - lastShownMs < 0.9 * FRAME_MS && frameQueue.length < 3)) return;
  const [bitmap, step, index] = frameQueue.shift();
  lastShownMs = now;
  const canvas = $("video");
  if (canvas.width !== bitmap.width || canvas.height !== bitmap.height) {
    canvas.width = bitmap.width; canvas.height = bitmap.height;
  }
  canvas.getContext("2d").drawImage(bitmap, 0, 0);
  bitmap.close();
  dash.frames += 1; dash.lastFrameStep = step;
  reportDisplayed(step);
  $("frameinfo").textContent = `step ${step} · frame ${index} · t = ${(step * STEP_S).toFixed(2)} s`;
  voiceOnShown(step);
}

// ---- the avatar drawn here (render.mode: browser; static/avatar.js) ---------------------------------------
// Read by the tests: fps (measured over the last second), draws, received (motion frames), shownStep, ready.
const avatar = window.ecasAvatar = {fps: 0, draws: 0, received: 0, shownStep: -1, ready: false, error: "",
                                    player: null, loading: false};

function startAvatar() {
  send({type: "motion", enabled: true});
  if (avatar.loading) return;
  avatar.loading = true;
  $("video").hidden = true;
  $("avatar").hidden = false;
  import("/static/avatar.js")
    .then((m) => m.start($("avatar"), onAvatarStep))
    .catch((err) => { avatar.error = String(err && err.message || err);
                      $("frameinfo").textContent = `avatar: ${avatar.error}`; });
}

function onAvatarStep(step) {
  $("frameinfo").textContent = `step ${step} · drawn here · ${avatar.fps.toFixed(0)} fps`;
  voiceOnShown(step);
  reportDisplayed(step);
}

// ---- latency to the display: the page's clock against the dashboard's, and the steps it shows -------------
// Every second the page probes the dashboard's monotonic clock; the probe with the shortest round trip of the
// last CLOCK_PROBES gives the offset (NTP's rule: its error is at most half that round trip). Each newly shown
// step is reported with its display time on the dashboard's clock.
const CLOCK_PROBES = 20;
const clock = {probes: [], offsetMs: null, rttMs: null, lastStep: -1};
dash.displayReports = 0;

const pageNowMs = () => performance.timeOrigin + performance.now();

function probeClock() { send({type: "clock", t_page_ms: pageNowMs()}); }

function onClock(e) {
  const now = pageNowMs(), rtt = now - e.t_page_ms;
  clock.probes.push({rtt, offset: e.t_server_ns / 1e6 - (e.t_page_ms + now) / 2});
  if (clock.probes.length > CLOCK_PROBES) clock.probes.shift();
  const best = clock.probes.reduce((a, b) => (b.rtt < a.rtt ? b : a));
  clock.offsetMs = best.offset; clock.rttMs = best.rtt;
  dash.clockRttMs = best.rtt;
}

function reportDisplayed(step) {
  if (clock.offsetMs === null || step <= clock.lastStep) return;
  clock.lastStep = step;
  send({type: "displayed", step, t_server_ns: (pageNowMs() + clock.offsetMs) * 1e6, clock_rtt_ms: clock.rttMs});
  dash.displayReports += 1;
}

// ---- the agent's voice, on the picture's clock -----------------------------------------------------------
// A step's audio is scheduled ahead, to be heard when its step is shown. When is learnt from the steps shown so
// far: a step is shown STEP_MS after the one before it plus the display's jitter, so the time it is shown, minus
// STEP_MS times its index, is nearly constant; DisplayClock keeps a high quantile of that over the last steps
// (the voice had rather be a little late than early: lip-sync is noticed at 45 ms early, 125 ms late). The audio
// clock's own mapping to the page's clock (getOutputTimestamp: when a sample is heard, output latency included)
// turns that time into the audio context's time. VoiceScheduler then places each chunk: right after the one
// before it while that stays within the window around its target (the voice continuous: the chunks abut), else
// at its target, spliced with a short cross-fade (a late chunk starts part-way, its beginning dropped; one whose
// time has passed with its picture is skipped).
const STEP_MS = 1000 * STEP_S;
const DISPLAY_STEPS_KEPT = 50;      // 4 s of shown steps
const DISPLAY_QUANTILE = 0.75;
const VOICE_EARLY_S = 0.015;        // a chunk abuts the one before it while within this early ...
const VOICE_LATE_S = 0.025;         // ... or this late of its target; beyond, it is spliced to its target
const VOICE_FADE_S = 0.004;         // a splice's cross-fade
const VOICE_MARGIN_S = 0.01;        // the soonest a chunk is started after the audio clock's now
const VOICE_LOOKAHEAD_S = 0.15;     // chunks are scheduled this long before they are heard, no earlier

/** When steps are shown, from the ones shown so far (page ms). Pure arithmetic: tests drive it with any timeline. */
class DisplayClock {
  constructor() { this.offsets = []; this.offsetMs = null; }

  /** Step `step` was shown at `nowMs`. A new stream (an offset seconds away) starts afresh. */
  shown(step, nowMs) {
    const offset = nowMs - STEP_MS * step;
    if (this.offsetMs !== null && Math.abs(offset - this.offsetMs) > 2000) this.offsets = [];
    this.offsets.push(offset);
    if (this.offsets.length > DISPLAY_STEPS_KEPT) this.offsets.shift();
    const sorted = [...this.offsets].sort((a, b) => a - b);
    this.offsetMs = sorted[Math.min(sorted.length - 1, Math.floor(DISPLAY_QUANTILE * sorted.length))];
  }

  /** When step `step` will be shown (page ms), or null before any step was shown. */
  at(step) { return this.offsetMs === null ? null : STEP_MS * step + this.offsetMs; }
}

/** Where each chunk of the voice starts on the audio clock (s). Pure arithmetic, as DisplayClock. */
class VoiceScheduler {
  constructor() { this.stats = {abutted: 0, spliced: 0, skipped: 0}; this.reset(); }

  /** Forget the chunks placed (the voice was silenced): the next one is placed at its target. */
  reset() { this.playhead = 0; this.lastStep = -Infinity; }

  /** Step `step`'s chunk of `durationS`, due to start at `targetS`, the audio clock at `nowS`: null (skipped:
   *  its time passed) or {at, end, offsetS (its first offsetS seconds dropped), abuts (it starts where the chunk
   *  before it ends; else it fades in, and a chunk still playing fades out where it overlaps or at its end)}. */
  place(step, durationS, targetS, nowS) {
    const earliest = nowS + VOICE_MARGIN_S;
    const error = this.playhead - targetS;  // > 0: after the chunk before it, this one would be late
    if (step === this.lastStep + 1 && this.playhead >= earliest && error >= -VOICE_EARLY_S && error <= VOICE_LATE_S) {
      this.stats.abutted += 1;
      return this.commit(step, {at: this.playhead, offsetS: 0, abuts: true}, durationS);
    }
    const at = Math.max(targetS, earliest), offsetS = at - targetS;
    if (offsetS > durationS - VOICE_FADE_S) { this.stats.skipped += 1; return null; }
    this.stats.spliced += 1;
    return this.commit(step, {at, offsetS, abuts: false}, durationS);
  }

  commit(step, placed, durationS) {
    this.playhead = placed.at + durationS - placed.offsetS;
    this.lastStep = step;
    return {...placed, end: this.playhead};
  }
}

const audio = {ctx: null, pending: new Map(), display: new DisplayClock(), scheduler: new VoiceScheduler(),
               scheduled: new Map(), last: null, sources: new Set(), shownStep: -1};
dash.voice = audio.scheduler.stats;
dash.DisplayClock = DisplayClock; dash.VoiceScheduler = VoiceScheduler;  // for the tests

function ensureAudio() {
  if (!audio.ctx) audio.ctx = new AudioContext({sampleRate: 24000});
  audio.ctx.resume();
  $("sound").checked = true;
  send({type: "audio", enabled: true});
}

function onAudio(step, pcm) {
  if (!audio.ctx) return;
  audio.pending.set(step, pcm);
  for (const s of audio.pending.keys()) if (s < step - 50) audio.pending.delete(s);  // never shown: dropped
  scheduleVoice();
}

/** The audio clock's time (s) at which a sample is heard at page time `ms`, by the output's own timestamp. */
function audioTimeAt(ms) {
  const out = audio.ctx.getOutputTimestamp();
  if (!out || !out.performanceTime) return null;
  return out.contextTime + (ms - out.performanceTime) / 1000;
}

/** The pending chunks (step -> samples) whose time is near, oldest first, taken out of `pending` and placed:
 *  [{step, pcm, placed}] (placed null: skipped). `shownAtMs(step)` and `audioTimeAt(ms)` give a step's time on
 *  the page's and then the audio clock (null: not known yet); `nowS` is the audio clock's now. */
function dueChunks(pending, scheduler, shownAtMs, audioTimeAt, nowS) {
  const out = [];
  for (const step of [...pending.keys()].sort((a, b) => a - b)) {
    const ms = shownAtMs(step), target = ms === null ? null : audioTimeAt(ms);
    if (target === null || target - nowS > VOICE_LOOKAHEAD_S) break;  // later (in order: so are the next ones)
    const pcm = pending.get(step);
    pending.delete(step);
    out.push({step, pcm, placed: scheduler.place(step, pcm.length / 24000, target, nowS)});
  }
  return out;
}
dash.dueChunks = dueChunks;  // for the tests

/** Schedule the chunks whose time is near (on each chunk received, step shown and 5 ms tick). */
function scheduleVoice() {
  if (!audio.ctx || !audio.pending.size) return;
  const due = dueChunks(audio.pending, audio.scheduler, (s) => audio.display.at(s), audioTimeAt, audio.ctx.currentTime);
  for (const {step, pcm, placed} of due) if (placed) playChunk(step, pcm, placed);
}

function playChunk(step, pcm, {at, end, offsetS, abuts}) {
  const ctx = audio.ctx, buffer = ctx.createBuffer(1, pcm.length, 24000), data = buffer.getChannelData(0);
  for (let i = 0; i < pcm.length; i++) data[i] = pcm[i] / 32768;
  const src = ctx.createBufferSource(), gain = ctx.createGain();
  src.buffer = buffer;
  src.connect(gain).connect(ctx.destination);
  const last = audio.last;
  if (!abuts) {  // fade this one in; the one before out, where it overlaps this one or where it ends
    gain.gain.setValueAtTime(0, at);
    gain.gain.linearRampToValueAtTime(1, at + VOICE_FADE_S);
  }
  if (!abuts && last && last.end > ctx.currentTime) {
    const from = Math.max(ctx.currentTime, Math.min(at, last.end - VOICE_FADE_S));
    last.gain.gain.setValueAtTime(1, from);
    last.gain.gain.linearRampToValueAtTime(0, from + VOICE_FADE_S);
    if (at < last.end) last.src.stop(from + VOICE_FADE_S);
  }
  src.start(at, offsetS);
  audio.last = {src, gain, end};
  audio.sources.add(src);
  src.onended = () => audio.sources.delete(src);
  audio.scheduled.set(step, at - offsetS);  // when the step's own start is heard
  if (audio.scheduled.size > 100) audio.scheduled.delete(audio.scheduled.keys().next().value);
  dash.audioSteps += 1; dash.audioLastStep = step;
}

/** Silence the voice now (the run stopped): the chunks scheduled ahead and the ones pending. */
function silenceVoice() {
  for (const src of audio.sources) src.stop();
  audio.sources.clear(); audio.pending.clear(); audio.last = null;
  audio.scheduler.reset();
}

/** Step `step` is shown now: it teaches the display clock, and its voice's offset is measured. */
function voiceOnShown(step) {
  if (step <= audio.shownStep && step >= audio.shownStep - 50) return;  // the step's second frame (server mode)
  if (step < audio.shownStep) audio.scheduled.clear();  // a new run: its steps start again
  audio.shownStep = step;
  audio.display.shown(step, performance.now());
  if (!audio.ctx) return;
  if (audio.scheduled.has(step)) measureAvOffset(audio.scheduled.get(step));
  scheduleVoice();
}

// The voice's offset from the picture (ms; > 0: the voice comes later): when the step being shown now starts to
// sound, by the audio clock's own mapping of its output to the page's clock. It includes the audio output's own
// latency (audioOutputLatencyMs, as the AudioContext reports it).
dash.avOffsetsMs = [];
const AV_OFFSETS_KEPT = 1000;

function measureAvOffset(atS) {
  const out = audio.ctx.getOutputTimestamp();
  if (!out || !out.performanceTime) return;
  const heard = out.performanceTime + 1000 * (atS - out.contextTime);
  dash.avOffsetMs = Math.round(heard - performance.now());
  dash.audioOutputLatencyMs = Math.round(1000 * ((audio.ctx.outputLatency || 0) + (audio.ctx.baseLatency || 0)));
  dash.avOffsetsMs.push(dash.avOffsetMs);
  if (dash.avOffsetsMs.length > AV_OFFSETS_KEPT) dash.avOffsetsMs.shift();
}

// ---- the browser's microphone as the user's voice (launch.py --browser-mic) ------------------------------
const mic = {on: false, ctx: null, stream: null, seq: 0};

$("mic").onclick = () => (mic.on ? stopMic() : startMic());

async function startMic() {
  $("micinfo").textContent = "";
  if (!navigator.mediaDevices) {
    $("micinfo").textContent = "no microphone here: browsers allow it on https or localhost only";
    return;
  }
  try {
    mic.stream = await navigator.mediaDevices.getUserMedia(
      {audio: {echoCancellation: true, noiseSuppression: true, autoGainControl: true, channelCount: 1}});
    mic.ctx = new AudioContext({sampleRate: 24000});
    await mic.ctx.audioWorklet.addModule("/static/mic-worklet.js");
    const node = new AudioWorkletNode(mic.ctx, "mic-blocks");
    const mute = mic.ctx.createGain();
    mute.gain.value = 0;
    mic.ctx.createMediaStreamSource(mic.stream).connect(node).connect(mute).connect(mic.ctx.destination);
    node.port.onmessage = (ev) => sendMic(ev.data);
  } catch (err) {
    stopMic();
    $("micinfo").textContent = `microphone unavailable: ${err.message}`;
    return;
  }
  mic.on = true;
  $("mic").classList.add("on"); $("mic").textContent = "🎤 Mute";
  send({type: "mic", enabled: true});
  ensureAudio();
}

function stopMic() {
  if (mic.stream) mic.stream.getTracks().forEach((t) => t.stop());
  if (mic.ctx) mic.ctx.close();
  Object.assign(mic, {on: false, ctx: null, stream: null});
  $("mic").classList.remove("on"); $("mic").textContent = "🎤 Talk";
  send({type: "mic", enabled: false});
}

function sendMic(block) {
  if (!mic.on || !ws || ws.readyState !== WebSocket.OPEN) return;
  const buf = new ArrayBuffer(8 + 2 * block.length);
  const view = new DataView(buf);
  view.setUint8(0, KIND_MIC); view.setUint32(4, mic.seq++, true);
  const pcm = new Int16Array(buf, 8);
  for (let i = 0; i < block.length; i++) pcm[i] = Math.max(-1, Math.min(1, block[i])) * 32767;
  ws.send(buf);
  dash.micBlocks += 1;
}

// ---- transcript -----------------------------------------------------------------------------------------
const turnEls = new Map();

function onTurn(t) {
  let el = turnEls.get(t.id);
  const box = $("turns");
  const atBottom = box.scrollHeight - box.scrollTop - box.clientHeight < 40;
  if (!el) {
    el = document.createElement("div");
    el.className = `msg ${t.speaker}`;
    turnEls.set(t.id, el);
    box.appendChild(el);
    for (const [id, old] of turnEls) {  // a long session keeps its last MAX_TURNS turns on the page
      if (turnEls.size <= MAX_TURNS) break;
      old.remove(); turnEls.delete(id);
    }
  }
  const when = (t.start_step * STEP_S).toFixed(1);
  const who = `<div class="who">${t.speaker === "user" ? "you" : "agent"} · ${when} s</div>`;
  const words = t.words.map((w, i) => `<span${i === t.interrupted_at ? ' class="cut"' : ""}>${esc(w)}</span>`);
  const partial = t.partial ? ` <span class="partial">${esc(t.partial)}…</span>` : "";
  const tag = t.interrupted_at !== null ? '<span class="tag">✂ interrupted</span>' : "";
  el.innerHTML = who + words.join(" ") + partial + tag;
  el.dataset.words = t.words.length;
  dash.words = [...turnEls.values()].reduce((n, e) => n + Number(e.dataset.words), 0);
  if (atBottom) box.scrollTop = box.scrollHeight;
}

function esc(s) { return s.replace(/[&<>"]/g, (c) => ({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;"}[c])); }

// ---- voice activity and the floor -----------------------------------------------------------------------
function onVad(e) {
  dash.userDbfs = e.user_dbfs;
  $("levelbar").style.width = `${Math.max(0, Math.min(100, (e.user_dbfs + 60) / 60 * 100))}%`;
  $("level").textContent = e.user_dbfs <= -89 ? "-∞ dB" : `${e.user_dbfs.toFixed(0)} dB`;
  $("vadbar").style.width = `${Math.round(e.prob * 100)}%`;
  $("vadstate").textContent = e.state;
  $("agentspeaking").className = "dot" + (e.agent_speaking ? " on" : "");
  $("agentstate").textContent = e.interrupted ? "interrupted" : e.agent_speaking ? "speaking" : "silent";
  $("turnstate").textContent = e.turn; $("turnstate").className = "turn " + e.turn;
  turnHistory.push(e.turn);
  if (turnHistory.length > HISTORY) turnHistory.shift();
  stripDirty = true;
}

function drawStrip() {
  const c = $("turnstrip"), g = c.getContext("2d"), w = c.width / HISTORY;
  g.fillStyle = TURN_COLORS.none; g.fillRect(0, 0, c.width, c.height);
  turnHistory.forEach((t, i) => {
    g.fillStyle = TURN_COLORS[t];
    g.fillRect((HISTORY - turnHistory.length + i) * w, 0, Math.ceil(w), c.height);
  });
}

// ---- latency chart --------------------------------------------------------------------------------------
let displayLatency = [];  // recent display_latency events: capture to this page's display
dash.displaySamples = 0;

function onDisplayLatency(e) {
  displayLatency.push(e);
  if (displayLatency.length > HISTORY) displayLatency.shift();
  dash.displaySamples += 1;
  chartDirty = true;
}

function onLatency(e) {
  latency.push(e);
  if (latency.length > HISTORY) latency.shift();
  dash.latencySamples += 1;
  chartDirty = true;
}

function niceMax(v) {
  for (const m of [40, 80, 120, 160, 200, 240, 400, 600, 800, 1200, 1600, 2000, 4000]) if (v <= m) return m;
  return Math.ceil(v / 4000) * 4000;
}

function drawChart() {
  const c = $("chart");
  const dpr = window.devicePixelRatio || 1;
  const width = Math.round(c.clientWidth * dpr), height = Math.round(c.clientHeight * dpr);
  if (c.width !== width || c.height !== height) { c.width = width; c.height = height; }
  const g = c.getContext("2d");
  const left = 44 * dpr, bottom = 18 * dpr, top = 6 * dpr;
  const plotW = width - left - 8 * dpr, plotH = height - bottom - top;
  g.clearRect(0, 0, width, height);
  const yMax = niceMax(Math.max(1, ...latency.map((e) => e.e2e_ms)));
  const x = (i) => left + (i + HISTORY - latency.length) * plotW / (HISTORY - 1);
  const y = (ms) => top + plotH * (1 - Math.min(ms, yMax) / yMax);
  g.font = `${11 * dpr}px system-ui`; g.fillStyle = "#8a96a3"; g.strokeStyle = "#2a323b"; g.lineWidth = 1;
  for (let k = 0; k <= 4; k++) {
    const ms = yMax * k / 4;
    g.beginPath(); g.moveTo(left, y(ms)); g.lineTo(width, y(ms)); g.stroke();
    g.fillText(`${ms} ms`, 2 * dpr, y(ms) + 4 * dpr);
  }
  g.fillText("step →", width - 50 * dpr, height - 4 * dpr);
  if (latency.length) {
    const base = latency.map(() => 0);
    dash.pipeline.forEach((stage, si) => {   // stacked: each stage's share on top of the previous ones
      g.beginPath();
      const share = (e) => Math.max(0, e.stages[stage] || 0);
      latency.forEach((e, i) => g.lineTo(x(i), y(base[i] + share(e))));
      for (let i = latency.length - 1; i >= 0; i--) g.lineTo(x(i), y(base[i]));
      g.closePath(); g.fillStyle = STAGE_COLORS[si] + "cc"; g.fill();
      latency.forEach((e, i) => { base[i] += share(e); });
    });
    g.beginPath(); g.strokeStyle = "#ffffff"; g.lineWidth = 1.5 * dpr;
    latency.forEach((e, i) => (i ? g.lineTo(x(i), y(e.e2e_ms)) : g.moveTo(x(i), y(e.e2e_ms))));
    g.stroke();
    const sorted = latency.map((e) => e.e2e_ms).sort((a, b) => a - b);
    const pct = (p) => sorted[Math.min(sorted.length - 1, Math.floor(p / 100 * sorted.length))].toFixed(0);
    $("latencystats").textContent = `end to end: last ${latency[latency.length - 1].e2e_ms.toFixed(0)} ms · ` +
      `p50 ${pct(50)} · p95 ${pct(95)} ms over ${latency.length} steps`;
    const index = new Map(latency.map((e, i) => [e.step, i]));  // a step's place on the chart's x axis
    const shown = displayLatency.filter((e) => index.has(e.step));
    if (shown.length) {  // to the display: a dashed yellow line
      const xs = (step) => x(index.get(step));
      g.beginPath(); g.strokeStyle = "#f5d442"; g.setLineDash([4 * dpr, 3 * dpr]);
      shown.forEach((e, i) => (i ? g.lineTo(xs(e.step), y(e.e2e_ms)) : g.moveTo(xs(e.step), y(e.e2e_ms))));
      g.stroke(); g.setLineDash([]);
      const d = shown.map((e) => e.e2e_ms).sort((a, b) => a - b);
      const dp = (p) => d[Math.min(d.length - 1, Math.floor(p / 100 * d.length))].toFixed(0);
      $("latencystats").textContent += ` · to the display: p50 ${dp(50)} · p95 ${dp(95)} ms`;
    }
    dash.chartLastStep = latency[latency.length - 1].step;
  }
  dash.chartDraws += 1;
}

// ---- counters -------------------------------------------------------------------------------------------
let stageStates = {};

function renderStageStates(states) { stageStates = states || stageStates; }

function onCounters(e) {
  renderStageStates(e.states);
  const rows = Object.entries(e.stages).map(([name, c]) => [name, stageStates[name] || "", c]);
  const own = e.dashboard;
  rows.push(["dashboard", `${own.pages || 0} page(s)`, {handled: own.received_frames, dropped: own.dropped,
    lost: own.lost, dropped_frames: own.skipped_frames,
    decode_errors: (own.decode_errors || 0) + (own.bad_frames || 0)}]);
  $("counters").tBodies[0].innerHTML = rows.map(([name, state, c]) => {
    const errors = (c.decode_errors || 0) + (c.handler_errors || 0);
    const cell = (v) => `<td${v ? ' class="bad"' : ""}>${v || 0}</td>`;
    return `<tr><td>${name}</td><td>${state}</td><td>${c.handled || 0}</td>${cell(c.dropped)}${cell(c.lost)}` +
      `${cell(c.dropped_frames)}${cell(errors)}</tr>`;
  }).join("");
}

// ---- main -----------------------------------------------------------------------------------------------
setInterval(() => { showFrames(); scheduleVoice(); }, 5);
setInterval(probeClock, 1000);
setInterval(() => {
  if (chartDirty) { chartDirty = false; drawChart(); }
  if (stripDirty) { stripDirty = false; drawStrip(); }
}, 100);
connect();
