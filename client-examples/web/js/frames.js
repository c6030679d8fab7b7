// When the page draws.
//
// The page draws a frame only when what it shows changed: drawIfChanged() compares the camera with
// the one last drawn (orbit controls, fly-to), and whatever else changes the picture (a tile came,
// went or changed visibility, a control changed the materials or the shapes, a resize) calls
// invalidate(). An idle page then costs no rendering (with a software renderer a frame of fine
// tiles takes about a second).

import * as THREE from 'three';

let needsFrame = true;
const drawnView = new THREE.Matrix4();
const drawnProjection = new THREE.Matrix4();

export function invalidate() {
  needsFrame = true;
}

/// Renders `scene` through `camera` when invalidated or the camera moved; true when it drew.
export function drawIfChanged(renderer, scene, camera) {
  if (!needsFrame && drawnView.equals(camera.matrixWorld) &&
      drawnProjection.equals(camera.projectionMatrix)) {
    return false;
  }
  needsFrame = false;
  drawnView.copy(camera.matrixWorld);
  drawnProjection.copy(camera.projectionMatrix);
  renderer.render(scene, camera);
  return true;
}
