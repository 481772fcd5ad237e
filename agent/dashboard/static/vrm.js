// A VRM 0.x / 1.0 rig the way VRM users expect it (--avatar FILE.vrm): loaded through @pixiv/three-vrm's
// VRMLoaderPlugin (MToon materials, spring bones, look-at, expressions, the normalized humanoid), served from
// /vendor/three-vrm/ and imported only when the avatar is a VRM.
//
// - The humanoid: each driven bone's normalized node (rest = identity in world axes) gets the world rotation
//   N_b = F G_j F^-1 · normalized_b from render/rig.py's spec (the same posed world rotation W'_b the raw bones get
//   for other rigs), as a local rotation under its driven ancestor's N; vrm.update() copies it onto the raw bones.
// - The face: the ARKit weights -> VRM preset expressions (render.rig.VRM_EXPRESSIONS, VRM_BLINK; docs/avatar.md)
//   through the expression manager, unless the file has ARKit-named morph targets (then those are driven).
// - The eyes look at the camera (vrm.lookAt), instead of following SMPL-X's eye joints.
// - vrm.update(dt) every pose: humanoid, look-at, expressions, spring bones, node constraints, materials.
import * as THREE from "three";

export const VRM_MODULE = "/vendor/three-vrm/lib/three-vrm.module.min.js";
const MAX_DT_S = 0.1;  // after a stall the spring bones take at most this step (a longer one can explode them)
const EYES = new Set(["leftEye", "rightEye"]);

/** Whether render.rig's spec describes a VRM (then the GLTFLoader needs registerVrm). */
export function isVrm(spec) {
  return spec.kind === "vrm0" || spec.kind === "vrm1";
}

/** Register three-vrm's loader plugin on a GLTFLoader. */
export async function registerVrm(loader) {
  const {VRMLoaderPlugin} = await import(VRM_MODULE);
  loader.register((parser) => new VRMLoaderPlugin(parser));
}

export class VrmDriver {
  /** `vrm`: gltf.userData.vrm; `rawBones`: the spec's bones' raw nodes, in the spec's order. */
  constructor(vrm, spec, rawBones, camera) {
    this.vrm = vrm;
    const nameOf = new Map(Object.entries(vrm.humanoid.rawHumanBones).map(([name, bone]) => [bone.node, name]));
    this.bones = spec.bones.map((b, k) => {
      const name = nameOf.get(rawBones[k]);
      const node = name && vrm.humanoid.getNormalizedBoneNode(name);
      if (!node) throw new Error(`VRM: node ${b.node} of the retargeting spec is not a humanoid bone`);
      return {name, node, joint: b.joint, ancestor: b.ancestor, normalized: new THREE.Quaternion().fromArray(b.normalized),
              lookAtOwned: Boolean(vrm.lookAt) && EYES.has(name)};
    });
    this.hips = vrm.humanoid.getNormalizedBoneNode("hips");
    this.world = this.bones.map(() => new THREE.Quaternion());
    this.expressions = spec.vrm.expressions.filter(([name]) => vrm.expressionManager?.getExpression(name));
    this.blink = spec.vrm.blink.length ? spec.vrm.blink : null;
    if (vrm.lookAt) {
      vrm.lookAt.target = camera;
      vrm.lookAt.autoUpdate = true;
    }
    this.lastUpdate = null;
    this._q = new THREE.Quaternion();
  }

  /** Pose the normalized humanoid: `global[j]` SMPL-X's global rotations, `yaw` / `yawInverse` the frame turn F,
   *  `hipsWorld` the hips' position in the scene. */
  pose(global, yaw, yawInverse, hipsWorld) {
    this.bones.forEach((b, k) => {
      const w = this.world[k].copy(yaw).multiply(global[b.joint]).multiply(yawInverse).multiply(b.normalized);
      if (b.lookAtOwned) return;
      if (b.ancestor < 0) b.node.quaternion.copy(w);
      else b.node.quaternion.copy(this._q.copy(this.world[b.ancestor]).invert().multiply(w));
    });
    this.hips.position.copy(hipsWorld);
  }

  /** The expressions from the ARKit weights: `weight(i)` is ARKit weight i at the playhead. */
  face(weight) {
    const manager = this.vrm.expressionManager;
    if (!manager) return;
    for (const [name, terms] of this.expressions) {
      let value = 0;
      for (const [i, gain] of terms) value += gain * weight(i);
      manager.setValue(name, Math.min(1, Math.max(0, value)));
    }
    if (this.blink) {  // blink = both eyes' common part, blinkLeft / blinkRight the rest of each (render.rig)
      const [left, right] = this.blink.map((i) => Math.min(1, Math.max(0, weight(i))));
      const both = Math.min(left, right);
      manager.setValue("blink", both);
      manager.setValue("blinkLeft", left - both);
      manager.setValue("blinkRight", right - both);
    }
  }

  /** vrm.update with the time since the last one (the first one: 0). */
  update(now = performance.now()) {
    const dt = this.lastUpdate === null ? 0 : Math.min(MAX_DT_S, Math.max(0, (now - this.lastUpdate) / 1000));
    this.lastUpdate = now;
    this.vrm.update(dt);
  }

  /** Test hook: the expression manager's values, the look-at angles and the eye's turn, the spring joints (world, and in the head's
   *  frame), the materials' types. */
  state() {
    const manager = this.vrm.expressionManager;
    const expressions = {};
    for (const e of manager ? manager.expressions : []) expressions[e.expressionName] = manager.getValue(e.expressionName);
    const head = this.vrm.humanoid.getRawBoneNode("head");
    head.updateWorldMatrix(true, false);
    const springs = [...(this.vrm.springBoneManager?.joints ?? [])].map((j) => {
      const p = j.bone.getWorldPosition(new THREE.Vector3());
      return {name: j.bone.name, world: p.toArray(), inHead: head.worldToLocal(p.clone()).toArray()};
    });
    const materials = new Set();
    this.vrm.scene.traverse((o) => { if (o.isMesh) [].concat(o.material).forEach((m) => materials.add(m.isMToonMaterial ? "MToonMaterial" : m.type)); });
    const eye = this.vrm.humanoid.getRawBoneNode("leftEye"), rest = this.vrm.humanoid.rawRestPose.leftEye?.rotation;
    const eyeTurnDeg = eye && rest  // the left eye's turn away from its rest rotation (the look-at's doing)
      ? 2 * Math.acos(Math.min(1, Math.abs(eye.quaternion.dot(this._q.fromArray(rest))))) * 180 / Math.PI : null;
    return {expressions, springs, materials: [...materials], eyeTurnDeg,
            lookAt: this.vrm.lookAt ? {yaw: this.vrm.lookAt.yaw, pitch: this.vrm.lookAt.pitch} : null,
            meta: this.vrm.meta?.metaVersion ?? null};
  }
}
