// Where the camera looks, and how it is moved.
//
// The model's frame decides (window.vsmViewer.frame, set once the tileset's root is in):
// - `earth`: the model is earth-centred (ECEF, as `vsm import` makes of georeferenced rasters):
//   its bounding sphere reaches the shell 6200 to 6500 km from the origin where vsmd's terrain
//   route expects an ECEF model's vertices (the sphere's centre itself may lie far below: a model
//   the size of the US has it some 400 km under the surface). Orbit controls turn the camera
//   about the local vertical, away from the earth's centre.
// - `local`: any other model (organized point clouds in a local frame: a tunnel, a rock face). A
//   free-flying camera with no up to keep (three.js FlyControls: drag to look, W/S forward and
//   back, A/D and R/F sideways and up, Q/E roll, shift slow), so that it can go inside a tunnel;
//   its near plane is half the model's finest resolution (GET /v1/models/{m}: resolution.finest),
//   so that walls a sample spacing away are still drawn.
// The first view: `eye=X,Y,Z&at=X,Y,Z` (the model's coordinates, metres) when the URL gives them,
// else the whole tileset from above and to the south (view=top: straight down, north up).

import * as THREE from 'three';
import { FlyControls } from 'three/addons/controls/FlyControls.js';
import { params, state } from './settings.js';
import { finest } from './models.js';

/// Earth-centred: the bounding sphere meets the shell between these distances from the origin
/// (metres).
const EARTH_MIN = 6.2e6;
const EARTH_MAX = 6.5e6;

let camera = null;
let canvas = null;
let orbit = null;
let fly = null;
let finestResolution = null;
let modelRadius = 1;
const clock = new THREE.Clock();

export function initCamera(cameraArg, orbitArg, canvasArg) {
  camera = cameraArg;
  orbit = orbitArg;
  canvas = canvasArg;
}

/// Three numbers from the URL parameter `name` ("x,y,z"), or null.
function vectorParam(name) {
  const values = (params.get(name) || '').split(',').map(Number);
  return values.length === 3 && values.every(Number.isFinite) ? new THREE.Vector3(...values)
    : null;
}

/// The model's finest resolution (metres between grid neighbours), for the near plane.
export function setFinestResolution(metres) {
  finestResolution = metres > 0 ? metres : null;
  if (fly) {
    setClipping(modelRadius);
  }
}

/// Near and far planes for a model of `radius`: in a local frame tied to the finest resolution.
function setClipping(radius) {
  if (fly && finestResolution !== null) {
    camera.near = finestResolution / 2;
  } else {
    camera.near = radius / 1000;
  }
  camera.far = radius * 100;
  camera.updateProjectionMatrix();
  state.near = camera.near;
}

/// Points the camera from where it is at `target` (`up` the orbit's axis, the screen's up).
function aim(target, up, radius) {
  camera.up.copy(up);
  setClipping(radius);
  if (fly) {
    camera.lookAt(target);
  } else {
    orbit.target.copy(target);
    orbit.update();
  }
}

/// The local vertical at `point`: away from the earth's centre, or +z in a local frame.
function upAt(point) {
  return point.lengthSq() > 1e10 ? point.clone().normalize() : new THREE.Vector3(0, 0, 1);
}

/// Looks at a sphere (centre, radius) from above and to the south (view=top: straight down,
/// north up, the sphere filling the view).
function lookAt(centre, radius) {
  const up = upAt(centre);
  const north = new THREE.Vector3(0, 0, 1).sub(up.clone().multiplyScalar(up.z));
  if (north.lengthSq() < 1e-8) {
    north.set(0, 1, 0);
  }
  north.normalize();
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
  aim(centre, up, radius);
}

/// Replaces the orbit controls by a free-flying camera (a model in a local frame).
function useFreeCamera(radius) {
  orbit.enabled = false;
  orbit.dispose();
  fly = new FlyControls(camera, canvas);
  fly.dragToLook = true;
  fly.movementSpeed = radius / 4;  // metres per second: the model's diameter in 8 s
  fly.rollSpeed = Math.PI / 6;
}

/// Moves the camera by the controls (the free-flying one moves with time).
export function updateControls() {
  const delta = clock.getDelta();
  if (fly) {
    fly.update(Math.min(delta, 0.1));
  }
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

/// Decides the model's frame and places the camera once the tileset's root is in; false while it
/// is not.
export function placeCamera(tiles) {
  const sphere = new THREE.Sphere();
  if (!tiles.getBoundingSphere(sphere)) {
    return false;
  }
  const centre = sphere.center.clone().applyMatrix4(tiles.group.matrixWorld);
  modelRadius = Math.max(sphere.radius, 1);
  const distance = centre.length();
  state.frame = distance + sphere.radius >= EARTH_MIN && distance - sphere.radius <= EARTH_MAX
    ? 'earth' : 'local';
  if (state.frame === 'local' && !fly) {
    useFreeCamera(modelRadius);
  }
  const eye = vectorParam('eye');
  const at = vectorParam('at');
  if (eye && at && !eye.equals(at)) {
    camera.position.copy(eye);
    aim(at, upAt(at), modelRadius);
  } else {
    lookAt(centre, modelRadius);
  }
  return true;
}
