// The avatar drawn in the page (render.mode: browser): three.js (npm, served from /vendor/three/) draws the
// skinned GLB at /avatar.glb (the built-in avatar, or the user's VRM / Mixamo rig: --avatar), driven by the
// motion stream (docs/motion_stream.md) at the display's rate through the retargeting spec at /avatar.json.
//
// Clock (Playout): the page plays motion frames on its own clock, a playout delay behind their arrival: the delay
// is a high quantile of the recent steps' arrival times (a jitter buffer, as a VoIP receiver's), so a step's first
// frame is drawn as soon as nearly every step has arrived, not a fixed number of frames behind the newest. The
// playhead speeds up or slows down a little to follow that delay, holds on the newest frame when a step is late,
// never moves 3 frames or more in one drawn frame (so no step is jumped over) and jumps only when it falls far
// behind. Between the two 25 fps frames around it, it interpolates (slerp of the joints' rotations,
// linear translation and morph weights). Once a frame is drawn, each step it shows for the first time is passed
// to onStep(step): the dashboard plays that step's voice then and reports the step displayed (end-to-end latency
// to the display).
//
// Drawing: at most MAX_FPS frames a second, and IDLE_FPS while nothing moves; morph targets and skinning are
// done on the CPU (CpuDeform): in SwiftShader, the software WebGL of a machine without a GPU, they were about
// 80 % of a frame's cost.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { VrmDriver, isVrm, registerVrm } from "/static/vrm.js";

const FRAME_MS = 40;
const FRAMES_PER_STEP = 2;
const HEADER_BYTES = 48, FRAME_FLOATS = 320, JOINTS = 55, EXPRESSIONS = 100, ARKIT = 52;
const VERSION = 1;
// The playout delay: ARRIVAL_QUANTILE of the last ARRIVALS_KEPT steps' arrival times (relative to their frame's
// place on a 25 fps clock), plus DELAY_MARGIN_MS. A step later than that makes the playhead hold, not skip. The
// backlog a stall releases at once counts as one arrival (its first step): a rare stall would otherwise hold
// the delay up for the whole window.
const ARRIVALS_KEPT = 100;       // 8 s of steps
const ARRIVAL_QUANTILE = 0.9;
const DELAY_MARGIN_MS = 5;
const RATE_GAIN = 0.5;           // playback rate 1 + RATE_GAIN * (frames behind the due frame), within [0.5, 2]
// Per drawn frame: below 3, at most one frame lies unseen between two drawn frames, never a whole step (2 frames)
const MAX_ADVANCE_FRAMES = 2.9;
const BATCH_MS = 20;             // steps arriving this soon after the one before: a stall's backlog
const MAX_BEHIND_FRAMES = 50;    // further behind the due frame than this (2 s): jump; less is caught up at 2x
const KEEP_FRAMES = 50;          // frames kept behind the playhead
const MAX_FPS = 30;              // drawing faster costs the agent's CPU and shows no motion the 25 fps frames lack
const IDLE_FPS = 2;              // while nothing moves (before the run, a held frame)
const FPS_SLACK_MS = 4;          // a display tick a little early still counts (60 Hz ticks -> 30 draws a second)
const BACKGROUND = 0x1b2026;
const FLOOR_TRANS_Y = 1.3;  // BEAT2's translation that puts SMPL-X's feet on the floor: the rest pose stands there
const CAMERA_OFFSET = [0, 0.05, 3.9];  // from the tracked pelvis (metres): the whole body in a 30° view
const CAMERA_TIME_MS = 400;           // the camera follows the pelvis with this time constant

// The 52 ARKit names in Apple's order (render.arkit.ARKIT_NAMES): the stream's weights come in this order.
export const ARKIT_NAMES = [
  "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft", "eyeSquintLeft",
  "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
  "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft", "jawRight", "jawOpen", "mouthClose", "mouthFunnel",
  "mouthPucker", "mouthLeft", "mouthRight", "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft",
  "mouthFrownRight", "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
  "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthPressLeft", "mouthPressRight",
  "mouthLowerDownLeft", "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight", "browDownLeft",
  "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight", "cheekPuff", "cheekSquintLeft",
  "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut",
];

// SMPL-X's joints (gesture.body.skeleton.JOINT_NAMES), the GLB's bone names.
const BODY = ["pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2", "left_ankle",
  "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar", "right_collar", "head",
  "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "jaw",
  "left_eye_smplhf", "right_eye_smplhf"];
const FINGERS = ["index", "middle", "pinky", "ring", "thumb"];
export const JOINT_NAMES = BODY.concat(...["left", "right"].map((side) =>
  FINGERS.flatMap((f) => [1, 2, 3].map((k) => `${side}_${f}${k}`))));

/** One motion packet (an ArrayBuffer slice) -> {step, first, frames: [{q, t, w}]}; throws on a wrong packet. */
export function decodePacket(buffer, offset = 0) {
  const view = new DataView(buffer, offset);
  const magic = String.fromCharCode(view.getUint8(0), view.getUint8(1), view.getUint8(2), view.getUint8(3));
  if (magic !== "ECMS") throw new Error(`motion packet: magic ${magic}`);
  const version = view.getUint16(4, true);
  if (version !== VERSION) throw new Error(`motion packet: version ${version}; this page reads version ${VERSION}`);
  const n = view.getUint16(6, true), step = view.getUint32(8, true), first = view.getUint32(40, true);
  if (view.getUint16(12, true) !== JOINTS || view.getUint16(14, true) !== EXPRESSIONS ||
      view.getUint16(16, true) !== ARKIT) throw new Error("motion packet: unexpected counts");
  const floats = new Float32Array(buffer.slice(offset + HEADER_BYTES, offset + HEADER_BYTES + n * FRAME_FLOATS * 4));
  const frames = [];
  for (let f = 0; f < n; f++) {
    const base = f * FRAME_FLOATS;
    const q = new Float32Array(JOINTS * 4);
    for (let j = 0; j < JOINTS; j++) axisAngleToQuaternion(floats, base + 3 * j, q, 4 * j);
    frames.push({
      q,
      t: floats.slice(base + 165, base + 168),
      w: floats.slice(base + 268, base + 268 + ARKIT),
    });
  }
  return {step, first, frames};
}

function axisAngleToQuaternion(src, at, dst, to) {
  const x = src[at], y = src[at + 1], z = src[at + 2];
  const angle = Math.hypot(x, y, z);
  const s = angle > 1e-8 ? Math.sin(angle / 2) / angle : 0.5;
  dst[to] = x * s; dst[to + 1] = y * s; dst[to + 2] = z * s; dst[to + 3] = Math.cos(angle / 2);
}

/** The page's motion clock: where the playhead (a fractional frame index) is at a given time. Pure arithmetic on
 *  the arrival times it is told (no three.js, no DOM), so tests can drive it with any timeline. */
export class Playout {
  constructor() { this.reset(); }

  reset() {
    this.offsets = [];   // recent steps' arrival time minus their first frame's place on the 25 fps clock, ms
    this.delayMs = 0;
    this.first = -1;     // the first frame received since the reset
    this.newest = -1;
    this.pos = null;
    this.lastNow = null;
    this.holding = false;
    this.lastArrival = undefined;
    this.stats = {delayMs: 0, holds: 0, heldMs: 0, jumps: 0, resets: 0};
  }

  /** A step's `count` frames from frame `first` arrived at `nowMs`. A stream that starts again from an earlier
   *  frame (a new run) resets the clock. */
  arrive(first, count, nowMs) {
    if (this.newest >= 0 && first + count - 1 < this.newest - MAX_BEHIND_FRAMES) {
      const resets = this.stats.resets + 1;
      this.reset();
      this.stats.resets = resets;
    }
    if (this.first < 0) this.first = first;
    const backlog = this.lastArrival !== undefined && nowMs - this.lastArrival < BATCH_MS;
    this.lastArrival = nowMs;
    this.newest = Math.max(this.newest, first + count - 1);
    if (backlog) return;
    this.offsets.push(nowMs - first * FRAME_MS);
    if (this.offsets.length > ARRIVALS_KEPT) this.offsets.shift();
    const sorted = [...this.offsets].sort((a, b) => a - b);
    this.delayMs = sorted[Math.min(sorted.length - 1, Math.floor(ARRIVAL_QUANTILE * sorted.length))] + DELAY_MARGIN_MS;
    this.stats.delayMs = this.delayMs;
  }

  /** The playhead at `nowMs` (called once per drawn frame), or null before any frame arrived. */
  advance(nowMs) {
    if (this.newest < 0) return null;
    // The playhead due now: a frame that arrived `delayMs` ago starts to show (the pose leaves the frame before it
    // towards it), so it is one frame behind the frame the delay makes due.
    const due = (nowMs - this.delayMs) / FRAME_MS - 1;
    if (this.pos === null || due - this.pos > MAX_BEHIND_FRAMES) {
      const pos = Math.max(this.first, Math.min(due, this.newest));  // start, or jump
      if (this.pos !== null && pos - this.pos > MAX_ADVANCE_FRAMES) this.stats.jumps += 1;
      this.pos = Math.max(this.pos ?? pos, pos);
    } else {
      const frames = (nowMs - this.lastNow) / FRAME_MS;  // at speed 1
      const rate = Math.min(2, Math.max(0.5, 1 + RATE_GAIN * (due - this.pos - frames)));
      const wanted = this.pos + Math.min(MAX_ADVANCE_FRAMES, rate * frames);
      const holding = wanted > this.newest;  // the next step is late: hold its predecessor's last frame
      if (holding && !this.holding) this.stats.holds += 1;
      if (holding) this.stats.heldMs += nowMs - this.lastNow;
      this.holding = holding;
      this.pos = Math.max(this.pos, Math.min(wanted, this.newest));
    }
    this.lastNow = nowMs;
    return this.pos;
  }
}

/** Which steps drawn frames show. A frame drawn at playhead p is interpolated from frame floor(p) and, when p is
 *  not whole, frame floor(p) + 1: it shows those of them that were received. A step is displayed by the first
 *  drawn frame that shows one of its frames; a step the playhead passed without that never was. With a playhead
 *  that advances at most MAX_ADVANCE_FRAMES a drawn frame, every step is shown unless the playhead jumped or the
 *  step's frames never arrived. */
export class StepTracker {
  constructor() { this.reset(); }

  reset() { this.reached = null; this.shown = 0; this.skipped = 0; }

  /** A frame at playhead `pos` was drawn, `has(frame)` tells which frames were received: the steps it reached,
   *  each {step, shown}, oldest first. */
  drawn(pos, has = () => true) {
    const k = Math.floor(pos);
    const front = pos > k ? k + 1 : k;
    const newest = Math.floor(front / FRAMES_PER_STEP);
    if (this.reached === null || newest < this.reached - 1) this.reached = newest - 1;  // start, or a new stream
    const showing = (pos > k ? [k, k + 1] : [k]).filter((f) => has(f)).map((f) => Math.floor(f / FRAMES_PER_STEP));
    const out = [];
    for (let step = this.reached + 1; step <= newest; step++) {
      const shown = showing.includes(step);
      if (shown) this.shown += 1; else this.skipped += 1;
      out.push({step, shown});
    }
    this.reached = Math.max(this.reached, newest);
    return out;
  }
}

/** Meshes deformed on the CPU: morph targets (the glTF's relative ones) added to the base positions and normals
 *  of the vertices they move when their weights change, then linear blend skinning of every vertex each frame,
 *  as three.js's vertex shader would do it (bindMatrixInverse * sum of weight * bone matrix * bindMatrix). The
 *  GPU then draws plain meshes: in SwiftShader, fetching the bone matrices from a texture for every vertex and
 *  evaluating every morph target were about 80 % of a frame's cost. */
class CpuDeform {
  constructor(root) {
    this.items = [];
    this._m = new THREE.Matrix4();
    const users = new Map();  // geometry -> meshes drawing it: a shared one is left to three.js
    root.traverse((o) => { if (o.isMesh && o.geometry) users.set(o.geometry, (users.get(o.geometry) || 0) + 1); });
    root.traverse((o) => {
      const g = o.geometry;
      if (!o.isMesh || !g || users.get(g) > 1 || !g.attributes.position) return;
      const morphed = g.morphAttributes.position && g.morphTargetsRelative && o.morphTargetInfluences;
      if (!morphed && !o.isSkinnedMesh) return;
      const names = ["position", "normal"].filter((n) => g.attributes[n]);
      if (names.some((n) => g.attributes[n].isInterleavedBufferAttribute)) return;  // left to three.js
      const base = Object.fromEntries(names.map((n) => [n, Float32Array.from(g.attributes[n].array)]));
      const item = {mesh: o, geometry: g, names, base, applied: null, targets: [], touched: new Int32Array(0),
                    source: Object.fromEntries(names.map((n) => [n, Float32Array.from(base[n])]))};  // morphed
      if (morphed) {
        const morphNames = names.filter((n) => g.morphAttributes[n]);
        item.targets = g.morphAttributes.position.map((_, i) => sparseTarget(g, morphNames, i));
        item.touched = Int32Array.from([...new Set(item.targets.flatMap((t) => [...t.index]))].sort((a, b) => a - b));
        g.morphAttributes = {};  // three.js now compiles the mesh's shader without morph targets
      }
      if (o.isSkinnedMesh) this.prepareSkin(item);
      this.items.push(item);
    });
  }

  prepareSkin(item) {
    const g = item.geometry, n = g.attributes.position.count;
    item.joints = new Uint16Array(4 * n);
    item.weights = new Float32Array(4 * n);
    for (let v = 0; v < n; v++) {
      for (let c = 0; c < 4; c++) {
        item.joints[4 * v + c] = g.attributes.skinIndex.getComponent(v, c);
        item.weights[4 * v + c] = g.attributes.skinWeight.getComponent(v, c);  // normalized integers: 0..1
      }
    }
    item.bones = new Float32Array(16 * item.mesh.skeleton.bones.length);
    item.mesh.isSkinnedMesh = false;  // drawn as a plain mesh from the positions skinned here
  }

  /** Pose every mesh: its morphs (if their weights changed), then its skin from the bones' world matrices (call
   *  after scene.updateMatrixWorld). */
  update() {
    for (const item of this.items) {
      const morphed = this.morph(item);
      if (item.joints) this.skin(item);
      else if (morphed) {
        for (const n of item.names) {
          item.geometry.attributes[n].array.set(item.source[n]);
          item.geometry.attributes[n].needsUpdate = true;
        }
      }
    }
  }

  morph(item) {
    const weights = item.mesh.morphTargetInfluences;
    if (!item.targets.length || (item.applied && weights.every((w, i) => w === item.applied[i]))) return false;
    item.applied = Array.from(weights);
    for (const name of item.names) {
      const dst = item.source[name], base = item.base[name];
      for (const v of item.touched) for (let c = 0; c < 3; c++) dst[3 * v + c] = base[3 * v + c];
      item.targets.forEach((t, i) => {
        const w = weights[i], delta = t[name];
        if (!w || !delta) return;
        for (let k = 0; k < t.index.length; k++) {
          const v = 3 * t.index[k];
          dst[v] += w * delta[3 * k]; dst[v + 1] += w * delta[3 * k + 1]; dst[v + 2] += w * delta[3 * k + 2];
        }
      });
    }
    return true;
  }

  skin(item) {
    const mesh = item.mesh, skeleton = mesh.skeleton, m = this._m, bones = item.bones;
    skeleton.bones.forEach((bone, b) => {  // in the bind space: bindMatrixInverse * world * boneInverse * bindMatrix
      m.multiplyMatrices(bone.matrixWorld, skeleton.boneInverses[b]).premultiply(mesh.bindMatrixInverse)
        .multiply(mesh.bindMatrix);
      bones.set(m.elements, 16 * b);  // column-major
    });
    const joints = item.joints, weights = item.weights, count = joints.length / 4;
    const normal = item.names.includes("normal");
    const p0 = item.source.position, p1 = item.geometry.attributes.position.array;
    const n0 = normal ? item.source.normal : p0, n1 = normal ? item.geometry.attributes.normal.array : null;
    for (let v = 0; v < count; v++) {
      const x = p0[3 * v], y = p0[3 * v + 1], z = p0[3 * v + 2];
      const a = n0[3 * v], b = n0[3 * v + 1], c = n0[3 * v + 2];
      let px = 0, py = 0, pz = 0, nx = 0, ny = 0, nz = 0;
      for (let k = 4 * v; k < 4 * v + 4; k++) {
        const w = weights[k];
        if (w === 0) continue;
        const e = 16 * joints[k];
        px += w * (bones[e] * x + bones[e + 4] * y + bones[e + 8] * z + bones[e + 12]);
        py += w * (bones[e + 1] * x + bones[e + 5] * y + bones[e + 9] * z + bones[e + 13]);
        pz += w * (bones[e + 2] * x + bones[e + 6] * y + bones[e + 10] * z + bones[e + 14]);
        nx += w * (bones[e] * a + bones[e + 4] * b + bones[e + 8] * c);
        ny += w * (bones[e + 1] * a + bones[e + 5] * b + bones[e + 9] * c);
        nz += w * (bones[e + 2] * a + bones[e + 6] * b + bones[e + 10] * c);
      }
      p1[3 * v] = px; p1[3 * v + 1] = py; p1[3 * v + 2] = pz;
      if (normal) { n1[3 * v] = nx; n1[3 * v + 1] = ny; n1[3 * v + 2] = nz; }
    }
    item.geometry.attributes.position.needsUpdate = true;
    if (normal) item.geometry.attributes.normal.needsUpdate = true;
  }
}

/** Target `i` of geometry `g` as the vertices it moves and their deltas, per attribute name. */
function sparseTarget(g, names, i) {
  const index = [];
  const count = g.attributes.position.count;
  const attrs = names.map((n) => g.morphAttributes[n][i]);
  for (let v = 0; v < count; v++) {
    if (attrs.some((a) => a.getX(v) !== 0 || a.getY(v) !== 0 || a.getZ(v) !== 0)) index.push(v);
  }
  const out = {index: Int32Array.from(index)};
  names.forEach((n, k) => {
    const delta = new Float32Array(3 * index.length);
    index.forEach((v, j) => { delta[3 * j] = attrs[k].getX(v); delta[3 * j + 1] = attrs[k].getY(v); delta[3 * j + 2] = attrs[k].getZ(v); });
    out[n] = delta;
  });
  return out;
}

export class AvatarPlayer {
  constructor(canvas, onStep) {
    this.canvas = canvas;
    this.onStep = onStep;
    this.frames = new Map();   // frame index -> {q, t, w}
    this.playout = new Playout();
    this.tracker = new StepTracker();
    this.pos = null;           // the playhead of the last drawn frame, in frames
    this.shownStep = -1;
    this.stats = {fps: 0, draws: 0, received: 0, shownFrame: -1, errors: 0, lastError: "", ready: false,
                  stepsShown: 0, stepsSkipped: 0, drawMs: 0, maxGapMs: 0};
    this.fpsWindow = [];
    this.lastDraw = null;      // when the last frame was drawn (ms)
    this.drawnKey = "";        // what it showed: redrawn only when that changes (or at IDLE_FPS)
    this._q0 = new THREE.Quaternion();
    this._q1 = new THREE.Quaternion();
  }

  /** Load the GLB and its retargeting spec (render.rig.Rig.spec: the built-in avatar or the user's rig). */
  async load(url, specUrl) {
    this.renderer = new THREE.WebGLRenderer({canvas: this.canvas, antialias: false, preserveDrawingBuffer: true});
    this.renderer.setPixelRatio(1);
    this.renderer.setSize(this.canvas.width, this.canvas.height, false);
    this.renderer.outputColorSpace = THREE.SRGBColorSpace;
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(BACKGROUND);
    this.camera = new THREE.PerspectiveCamera(30, this.canvas.width / this.canvas.height, 0.05, 50);
    this.target = null;  // the camera's smoothed pelvis position
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 1.8);
    sun.position.set(1, 2, 3);
    this.scene.add(sun);
    const fetchOk = (u) => fetch(u).then((r) => { if (!r.ok) throw new Error(`${u}: ${r.status}`); return r; });
    const [buffer, spec] = await Promise.all([
      fetchOk(url).then((r) => r.arrayBuffer()), fetchOk(specUrl).then((r) => r.json()),
    ]);
    const loader = new GLTFLoader();
    if (isVrm(spec)) await registerVrm(loader);  // three-vrm: MToon, spring bones, look-at, expressions
    const gltf = await loader.parseAsync(buffer, "");
    this.scene.add(gltf.scene);
    gltf.scene.updateMatrixWorld(true);
    const byNode = new Map();
    gltf.scene.traverse((o) => {
      const a = gltf.parser.associations.get(o);
      if (a && a.nodes !== undefined && !byNode.has(a.nodes)) byNode.set(a.nodes, o);
      if (o.isMesh) o.frustumCulled = false;  // a skinned mesh moves away from its bind-pose bounds
    });
    const meshesOf = (o) => (o.isMesh ? [o] : o.children.filter((c) => c.isMesh));
    this.spec = spec;
    this.kind = spec.kind;
    this.bones = spec.bones.map((b) => ({
      object: byNode.get(b.node), joint: b.joint, ancestor: b.ancestor,
      k: new THREE.Quaternion().fromArray(b.k), between: new THREE.Quaternion().fromArray(b.between),
    }));
    if (this.bones.some((b) => !b.object)) throw new Error(`${url}: a bone of the rig's spec is not in the file`);
    this.hips = byNode.get(spec.hips.node);
    this.hipsRest = new THREE.Vector3().fromArray(spec.hips.rest_world);
    this.hipsParentInverse = new THREE.Matrix4().fromArray(spec.hips.parent_inverse);
    this.face = spec.face.map((f) => ({meshes: meshesOf(byNode.get(f.node) || new THREE.Object3D()),
                                       target: f.target, terms: f.terms}));
    this.vrm = gltf.userData.vrm ? new VrmDriver(gltf.userData.vrm, spec, this.bones.map((b) => b.object), this.camera)
      : null;
    this.yaw = new THREE.Quaternion().setFromAxisAngle(new THREE.Vector3(0, 1, 0), spec.yaw_deg * Math.PI / 180);
    this.yawInverse = this.yaw.clone().invert();
    this.global = JOINT_NAMES.map(() => new THREE.Quaternion());
    this.local = JOINT_NAMES.map(() => new THREE.Quaternion());
    this.posed = this.bones.map(() => new THREE.Quaternion());
    this.rest = {q: new Float32Array(JOINTS * 4).fill(0), t: new Float32Array([0, FLOOR_TRANS_Y, 0]),
                 w: new Float32Array(ARKIT)};
    for (let j = 0; j < JOINTS; j++) this.rest.q[4 * j + 3] = 1;
    this.pose(this.rest, this.rest, 0);  // SMPL-X's rest pose until the motion arrives
    this.deform = new CpuDeform(gltf.scene);
    this.stats.ready = true;
  }

  /** A binary dashboard message's motion packet (after its 8-byte header). */
  push(buffer, offset) {
    let packet;
    try { packet = decodePacket(buffer, offset); } catch (err) {
      this.stats.errors += 1; this.stats.lastError = err.message; return;
    }
    const resets = this.playout.stats.resets;
    this.playout.arrive(packet.first, packet.frames.length, performance.now());
    if (this.playout.stats.resets !== resets) this.frames.clear();  // a new stream: the old frames are not its
    packet.frames.forEach((f, k) => this.frames.set(packet.first + k, f));
    this.stats.received += packet.frames.length;
  }

  /** Move the playhead to `now` (ms) and pose the avatar; the playhead, or null while there is nothing to show. */
  advance(now) {
    const pos = this.playout.advance(now);
    if (pos === null) return null;
    const k = Math.floor(pos), a = pos - k;
    let f0 = this.frames.get(k);
    for (let back = k - 1; !f0 && back >= k - KEEP_FRAMES; back--) f0 = this.frames.get(back);  // a gap: hold
    if (!f0) return null;
    const f1 = this.frames.get(k + 1) || f0;
    this.pose(f0, f1, a);
    for (const key of this.frames.keys()) if (key < k - KEEP_FRAMES) this.frames.delete(key);
    this.stats.shownFrame = k;
    return pos;
  }

  /** After a frame at playhead `pos` was drawn: the steps it showed first go to onStep, in order. */
  report(pos) {
    for (const {step, shown} of this.tracker.drawn(pos, (f) => this.frames.has(f))) {
      if (!shown) continue;  // jumped over: never on screen, so never reported as displayed
      this.shownStep = step;
      this.onStep(step);
    }
    this.stats.stepsShown = this.tracker.shown;
    this.stats.stepsSkipped = this.tracker.skipped;
  }

  /** Interpolate two frames and drive the rig: SMPL-X's global rotations, then each bone's world rotation
   *  W' = F G_j F^-1 K_b turned into its local rotation under its parent's posed world rotation (a VRM: through
   *  three-vrm's normalized bones, static/vrm.js). */
  pose(f0, f1, a) {
    const parents = this.spec.parents;
    for (let j = 0; j < JOINTS; j++) {
      this._q0.fromArray(f0.q, 4 * j);
      this._q1.fromArray(f1.q, 4 * j);
      this.local[j].slerpQuaternions(this._q0, this._q1, a);
      if (parents[j] < 0) this.global[j].copy(this.local[j]);
      else this.global[j].multiplyQuaternions(this.global[parents[j]], this.local[j]);
    }
    if (!this.vrm) this.bones.forEach((b, k) => {
      const w = this.posed[k].copy(this.yaw).multiply(this.global[b.joint]).multiply(this.yawInverse).multiply(b.k);
      const parentWorld = b.ancestor >= 0 ? this._q0.multiplyQuaternions(this.posed[b.ancestor], b.between)
        : this._q0.copy(b.between);
      b.object.quaternion.copy(parentWorld.invert().multiply(w));
    });
    const t = [0, 1, 2].map((i) => f0.t[i] + a * (f1.t[i] - f0.t[i]));
    const shift = new THREE.Vector3(t[0], t[1] - this.spec.hips.floor_trans_y, t[2]).applyQuaternion(this.yaw);
    const hipsWorld = shift.multiplyScalar(this.spec.hips.scale).add(this.hipsRest);
    if (this.vrm) this.vrm.pose(this.global, this.yaw, this.yawInverse, hipsWorld);
    else this.hips.position.copy(hipsWorld).applyMatrix4(this.hipsParentInverse);
    for (const {meshes, target, terms} of this.face) {
      let value = 0;
      for (const [i, gain] of terms) value += gain * (f0.w[i] + a * (f1.w[i] - f0.w[i]));
      value = Math.min(1, Math.max(0, value));
      for (const mesh of meshes) if (mesh.morphTargetInfluences) mesh.morphTargetInfluences[target] = value;
    }
    if (this.vrm) {
      this.vrm.face((i) => f0.w[i] + a * (f1.w[i] - f0.w[i]));
      this.vrm.update();
    }
  }

  /** Follow the pelvis (a causal low-pass), as the server's camera rig does. */
  track(now) {
    const pelvis = new THREE.Vector3();
    this.hips.getWorldPosition(pelvis);
    if (this.target === null) this.target = pelvis.clone();
    else this.target.lerp(pelvis, 1 - Math.exp(-(now - (this.lastDraw ?? now)) / CAMERA_TIME_MS));
    this.settled = this.target.distanceToSquared(pelvis) < 1e-8;  // the camera has caught up (0.1 mm)
    this.camera.position.set(...CAMERA_OFFSET).multiplyScalar(this.spec.hips.scale).applyQuaternion(this.yaw)
      .add(this.target);  // in front of the rig: a VRM 0.x model faces -z
    this.camera.lookAt(this.target);
  }

  /** One display tick (requestAnimationFrame's `now`, ms): draw a frame if one is due and something moved;
   *  true if a frame was drawn. */
  tick(now) {
    const since = this.lastDraw === null ? Infinity : now - this.lastDraw;
    if (since < 1000 / MAX_FPS - FPS_SLACK_MS) return this.countFps(now, false);
    const pos = this.advance(now);
    const key = pos === null ? "rest" : String(pos);
    if (key === this.drawnKey && this.settled && since < 1000 / IDLE_FPS) return this.countFps(now, false);
    const moving = key !== this.drawnKey && this.drawnKey !== "rest" && key !== "rest";
    this.drawnKey = key;
    const start = performance.now();
    this.scene.updateMatrixWorld(true);
    this.deform.update();
    this.track(now);
    this.renderer.render(this.scene, this.camera);
    this.stats.drawMs = performance.now() - start;
    if (moving && since < Infinity) this.stats.maxGapMs = Math.max(this.stats.maxGapMs, since);  // not idle
    this.lastDraw = now;
    this.stats.draws += 1;
    if (pos !== null) this.report(pos);
    return this.countFps(now, true);
  }

  /** Frames drawn in the last second, as a rate (it falls while nothing is drawn). */
  countFps(now, drawn) {
    if (drawn) this.fpsWindow.push(now);
    while (this.fpsWindow.length && this.fpsWindow[0] < now - 1000) this.fpsWindow.shift();
    this.stats.fps = this.fpsWindow.length;
    Object.assign(this.stats, {delayMs: this.playout.delayMs, holds: this.playout.stats.holds,
                               heldMs: this.playout.stats.heldMs, jumps: this.playout.stats.jumps});
    return drawn;
  }

  /** Test hook: pose one frame given as axis-angle (55 * 3), translation (3) and ARKit weights (52); returns each
   *  driven node's world position after the pose. */
  poseForTest(axisAngles, trans, weights) {
    const q = new Float32Array(JOINTS * 4);
    for (let j = 0; j < JOINTS; j++) axisAngleToQuaternion(axisAngles, 3 * j, q, 4 * j);
    const frame = {q, t: Float32Array.from(trans), w: Float32Array.from(weights)};
    this.pose(frame, frame, 0);
    this.scene.updateMatrixWorld(true);
    this.deform.update();
    const out = {};
    this.spec.bones.forEach((b, k) => { out[b.node] = this.bones[k].object.getWorldPosition(new THREE.Vector3()).toArray(); });
    return out;
  }

  /** Pixels that differ from the background, and a checksum of the image (tests compare two). */
  sample() {
    const c = document.createElement("canvas");
    c.width = this.canvas.width; c.height = this.canvas.height;
    const g = c.getContext("2d");
    g.drawImage(this.canvas, 0, 0);
    const px = g.getImageData(0, 0, c.width, c.height).data;
    const bg = new THREE.Color(BACKGROUND);
    const [br, bgc, bb] = [bg.r, bg.g, bg.b].map((v) => Math.round(v * 255));
    let different = 0, checksum = 0;
    for (let i = 0; i < px.length; i += 4) {
      if (Math.abs(px[i] - br) + Math.abs(px[i + 1] - bgc) + Math.abs(px[i + 2] - bb) > 24) different += 1;
      checksum = (checksum * 31 + px[i] + 3 * px[i + 1] + 7 * px[i + 2]) % 1000000007;
    }
    return {different, checksum, pixels: px.length / 4};
  }
}

/** Start drawing on `canvas`; returns the player (also window.ecasAvatar's source of numbers). */
export async function start(canvas, onStep, url = "/avatar.glb", specUrl = "/avatar.json") {
  const player = new AvatarPlayer(canvas, onStep);
  const state = window.ecasAvatar;
  state.player = player;
  try {
    await player.load(url, specUrl);
  } catch (err) {
    state.error = String(err && err.message || err);
    throw err;
  }
  const loop = (now) => {
    player.tick(now);
    Object.assign(state, player.stats, {shownStep: player.shownStep, kind: player.kind});
    requestAnimationFrame(loop);
  };
  requestAnimationFrame(loop);
  return player;
}
