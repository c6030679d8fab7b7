// Vertical exaggeration: every vertex of a tile lifted to k times its height above the WGS 84
// ellipsoid, and the normals to go with the shape (the GLB's at 1 when it has them, else computed
// per tile from its triangles).

import * as THREE from 'three';
import { state } from './settings.js';

// WGS 84.
const WGS84_A = 6378137.0;
const WGS84_B = 6356752.314245179;

const scratch = new THREE.Vector3();

/// Per vertex of a mesh (in its own frame) the vector that lifts it by its height above the WGS 84
/// ellipsoid (radially: the geocentric up is within 0.2 degrees of the normal), so that
/// exaggeration k puts the vertex at original + (k - 1) * lift. Uses the mesh's transform from its
/// tile (`toEcef`, mesh frame -> ECEF).
function liftOf(original, toEcef) {
  const inverse = new THREE.Matrix4().copy(toEcef).invert();
  const lift = new Float32Array(original.length);
  const p = new THREE.Vector3();
  for (let i = 0; i < original.length; i += 3) {
    p.set(original[i], original[i + 1], original[i + 2]).applyMatrix4(toEcef);
    const r = p.length();
    const horizontal = Math.hypot(p.x, p.y) / r;
    const vertical = p.z / r;
    const surface = (WGS84_A * WGS84_B) /
      Math.hypot(WGS84_B * horizontal, WGS84_A * vertical);
    // ECEF point lifted by its height, back in the mesh frame, minus the vertex.
    scratch.copy(p).multiplyScalar((2 * r - surface) / r).applyMatrix4(inverse);
    lift[i] = scratch.x - original[i];
    lift[i + 1] = scratch.y - original[i + 1];
    lift[i + 2] = scratch.z - original[i + 2];
  }
  return lift;
}

/// The mesh's position and normal attributes as plain float32 ones. vsmd's default GLBs are
/// quantized (KHR_mesh_quantization: uint16 positions scaled by the mesh's node, int8 normalized
/// normals, both interleaved with padding); shapeMesh() rewrites positions in place and copies
/// normals, which needs one float per component. Values stay in the mesh's frame (its matrices
/// keep the node's scale), read through getX/Y/Z, which undo the normalization.
function floatAttributes(geometry) {
  for (const name of ['position', 'normal']) {
    const attribute = geometry.getAttribute(name);
    if (!attribute || (!attribute.isInterleavedBufferAttribute &&
                       attribute.array instanceof Float32Array)) {
      continue;
    }
    const out = new Float32Array(attribute.count * 3);
    for (let i = 0; i < attribute.count; i++) {
      out[i * 3] = attribute.getX(i);
      out[i * 3 + 1] = attribute.getY(i);
      out[i * 3 + 2] = attribute.getZ(i);
    }
    geometry.setAttribute(name, new THREE.BufferAttribute(out, 3));
  }
}

/// Shapes a tile's mesh for the current exaggeration: positions, normals (the GLB's at 1 when it
/// has them, else computed) and bounds. Its userData.vsmToEcef is the mesh frame -> ECEF.
export function shapeMesh(mesh) {
  const geometry = mesh.geometry;
  const data = mesh.userData;
  const exaggeration = state.exaggeration;
  let position = geometry.attributes.position;
  if (!data.vsmOriginal) {
    floatAttributes(geometry);
    position = geometry.attributes.position;
    data.vsmOriginal = position.array.slice();
    data.vsmNormals = geometry.attributes.normal ? geometry.attributes.normal.array.slice() : null;
    data.vsmLift = null;
    data.vsmShapedFor = 1;
  }
  if (exaggeration !== data.vsmShapedFor || !geometry.attributes.normal) {
    if (exaggeration !== 1 && !data.vsmLift) {
      data.vsmLift = liftOf(data.vsmOriginal, data.vsmToEcef);
    }
    const k = exaggeration - 1;
    const out = position.array;
    for (let i = 0; i < out.length; i++) {
      out[i] = data.vsmOriginal[i] + (k === 0 ? 0 : k * data.vsmLift[i]);
    }
    position.needsUpdate = true;
    if (exaggeration === 1 && data.vsmNormals) {
      geometry.setAttribute('normal', new THREE.BufferAttribute(data.vsmNormals.slice(), 3));
    } else {
      geometry.computeVertexNormals();
    }
    geometry.computeBoundingBox();
    geometry.computeBoundingSphere();
    data.vsmShapedFor = exaggeration;
  }
}
