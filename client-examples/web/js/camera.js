// Where the camera looks: at the tileset once its root is in, and at a model's finest area when
// flown to. The orbit controls turn it about the model's up (away from the earth's centre).

import * as THREE from 'three';
import { state } from './settings.js';
import { finest } from './models.js';

let camera = null;
let controls = null;

export function initCamera(cameraArg, controlsArg) {
  camera = cameraArg;
  controls = controlsArg;
}

/// Looks at a sphere (ECEF centre, radius) from above and to the south (view=top: straight down,
/// north up, the sphere filling the view).
function lookAt(centre, radius) {
  // ECEF: "up" is away from the earth's centre (a local tileset without one looks along +z).
  const up = centre.lengthSq() > 1e10 ? centre.clone().normalize() : new THREE.Vector3(0, 0, 1);
  const north = new THREE.Vector3(0, 0, 1).sub(up.clone().multiplyScalar(up.z));
  if (north.lengthSq() < 1e-8) {
    north.set(0, 1, 0);
  }
  north.normalize();
  camera.up.copy(up);  // the orbit's axis
  if (state.view === 'top') {
    // A hair to the south of straight down (0.06 degrees): north is up on the screen, and the
    // orbit controls keep their axis.
    const half = THREE.MathUtils.degToRad(camera.fov / 2);
    const distance = radius / Math.min(Math.tan(half), Math.tan(half) * camera.aspect);
    camera.position.copy(centre)
      .addScaledVector(up, distance)
      .addScaledVector(north, -distance * 1e-3);
  } else {
    camera.position.copy(centre)
      .addScaledVector(up, radius * 1.6)
      .addScaledVector(north, -radius * 1.2);
  }
  camera.near = radius / 1000;
  camera.far = radius * 100;
  camera.updateProjectionMatrix();
  controls.target.copy(centre);
  controls.update();
}

/// Looks at the finest area of model `id` (read by readModels); false when it is not known.
export function flyTo(id) {
  const bounds = finest.get(id);
  if (!bounds) {
    return false;
  }
  const box = new THREE.Box3(new THREE.Vector3(...bounds.min), new THREE.Vector3(...bounds.max));
  const sphere = box.getBoundingSphere(new THREE.Sphere());
  lookAt(sphere.center, Math.max(sphere.radius, 1));
  state.flownTo = id;
  state.idle = false;
  return true;
}

/// Looks at the tileset's bounding volume; false while its root is not in.
export function placeCamera(tiles) {
  const sphere = new THREE.Sphere();
  if (!tiles.getBoundingSphere(sphere)) {
    return false;
  }
  lookAt(sphere.center.clone().applyMatrix4(tiles.group.matrixWorld), Math.max(sphere.radius, 1));
  return true;
}
