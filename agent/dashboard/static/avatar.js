// The avatar drawn in the page (render.mode: browser): three.js (npm, served from /vendor/three/) draws the
// skinned GLB at /avatar.glb (the built-in avatar, or the user's VRM / Mixamo rig: --avatar), driven by the
// motion stream (docs/motion_stream.md) at the display's rate through the retargeting spec at /avatar.json.
//
// Clock: the page plays motion frames on its own clock, about TARGET_LAG frames behind the newest one received,
// and interpolates between the two 25 fps frames around it (slerp of the joints' rotations, linear translation
// and morph weights). It speeds up or slows down a little to keep that lag and jumps when it falls far behind.
// When it starts showing a new step it calls onStep(step): the dashboard plays that step's voice then and
// reports the step shown (end-to-end latency to the display).
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { VrmDriver, isVrm, registerVrm } from "/static/vrm.js";

const FRAME_MS = 40;
const FRAMES_PER_STEP = 2;
const HEADER_BYTES = 48, FRAME_FLOATS = 320, JOINTS = 55, EXPRESSIONS = 100, ARKIT = 52;
const VERSION = 1;
// Frames behind the newest: a step's two frames arrive together every 80 ms, so a playhead moving at 25 fps needs
// two frames in hand to never wait for the next step; the first frame of a step then shows 40 ms after it arrives.
const TARGET_LAG = 2.0;
const MAX_LAG = 8;        // further behind than this (320 ms): jump
const KEEP_FRAMES = 50;   // frames kept behind the playhead
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

export class AvatarPlayer {
  constructor(canvas, onStep) {
    this.canvas = canvas;
    this.onStep = onStep;
    this.frames = new Map();   // frame index -> {q, t, w}
    this.newest = -1;
    this.pos = null;           // the playhead, in frames
    this.lastNow = null;
    this.shownStep = -1;
    this.stats = {fps: 0, draws: 0, received: 0, shownFrame: -1, errors: 0, lastError: "", ready: false};
    this.fpsWindow = [];
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
    this.stats.ready = true;
  }

  /** A binary dashboard message's motion packet (after its 8-byte header). */
  push(buffer, offset) {
    let packet;
    try { packet = decodePacket(buffer, offset); } catch (err) {
      this.stats.errors += 1; this.stats.lastError = err.message; return;
    }
    packet.frames.forEach((f, k) => this.frames.set(packet.first + k, f));
    this.newest = Math.max(this.newest, packet.first + packet.frames.length - 1);
    this.stats.received += packet.frames.length;
  }

  /** Move the playhead to `now` (ms) and pose the avatar; false while there is nothing to show. */
  advance(now) {
    if (this.newest < 0) return false;
    if (this.pos === null || this.newest - this.pos > MAX_LAG || this.newest < this.pos - MAX_LAG) {
      this.pos = Math.max(this.newest - TARGET_LAG, Math.min(...this.frames.keys()));  // start, or jump
    } else {
      const lag = this.newest - this.pos;
      const rate = Math.min(2, Math.max(0.5, 1 + 0.25 * (lag - TARGET_LAG)));
      this.pos = Math.min(this.newest, this.pos + rate * (now - this.lastNow) / FRAME_MS);
    }
    this.lastNow = now;
    const k = Math.floor(this.pos), a = this.pos - k;
    let f0 = this.frames.get(k);
    for (let back = k - 1; !f0 && back >= k - KEEP_FRAMES; back--) f0 = this.frames.get(back);  // a gap: hold
    if (!f0) return false;
    const f1 = this.frames.get(k + 1) || f0;
    this.pose(f0, f1, a);
    for (const key of this.frames.keys()) if (key < k - KEEP_FRAMES) this.frames.delete(key);
    this.stats.shownFrame = k;
    const step = Math.floor(k / FRAMES_PER_STEP);
    if (step > this.shownStep) {
      this.shownStep = step;
      this.onStep(step);
    }
    return true;
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
    this.lastDraw = now;
    this.camera.position.set(...CAMERA_OFFSET).multiplyScalar(this.spec.hips.scale).applyQuaternion(this.yaw)
      .add(this.target);  // in front of the rig: a VRM 0.x model faces -z
    this.camera.lookAt(this.target);
  }

  draw(now) {
    this.advance(now);
    this.scene.updateMatrixWorld(true);
    this.track(now);
    this.renderer.render(this.scene, this.camera);
    this.stats.draws += 1;
    this.fpsWindow.push(now);
    while (this.fpsWindow.length && this.fpsWindow[0] < now - 1000) this.fpsWindow.shift();
    this.stats.fps = this.fpsWindow.length > 1
      ? 1000 * (this.fpsWindow.length - 1) / (now - this.fpsWindow[0]) : 0;
  }

  /** Test hook: pose one frame given as axis-angle (55 * 3), translation (3) and ARKit weights (52); returns each
   *  driven node's world position after the pose. */
  poseForTest(axisAngles, trans, weights) {
    const q = new Float32Array(JOINTS * 4);
    for (let j = 0; j < JOINTS; j++) axisAngleToQuaternion(axisAngles, 3 * j, q, 4 * j);
    const frame = {q, t: Float32Array.from(trans), w: Float32Array.from(weights)};
    this.pose(frame, frame, 0);
    this.scene.updateMatrixWorld(true);
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
    player.draw(now);
    Object.assign(state, player.stats, {shownStep: player.shownStep, kind: player.kind});
    requestAnimationFrame(loop);
  };
  requestAnimationFrame(loop);
  return player;
}
