// What cesium.html and terrain.html share: a CesiumJS viewer with nothing fetched from anywhere
// but vsmd (no imagery or terrain of its own, no Cesium ion, no widgets), the camera as the pages
// report it, and one way to run a page and keep its error. Cesium is the global of
// vendor/cesium/Build/Cesium.js, which the page loads first.

/* global Cesium */

// No Cesium ion: nothing may ask it for a token, imagery or terrain.
Cesium.Ion.defaultAccessToken = '';

/// The model of the page (?model=ID); throws without one.
export function pageModel(params) {
  const model = params.get('model');
  if (!model) {
    throw new Error('no model given (?model=ID)');
  }
  return model;
}

/// A Cesium.Viewer in #view with `options` (terrainProvider at least) on top of the shared ones.
export function makeViewer(options) {
  return new Cesium.Viewer('view', {
    baseLayer: false,
    baseLayerPicker: false,
    geocoder: false,
    homeButton: false,
    sceneModePicker: false,
    navigationHelpButton: false,
    animation: false,
    timeline: false,
    fullscreenButton: false,
    infoBox: false,
    selectionIndicator: false,
    skyBox: false,
    skyAtmosphere: false,
    contextOptions: { webgl: { preserveDrawingBuffer: true } },
    // Draw when the scene changed (tiles, camera), not every frame: an idle page costs nothing.
    requestRenderMode: true,
    ...options,
  });
}

/// The matrices of the last frame drawn (column-major, world = ECEF) and the canvas size in CSS
/// pixels, so that a script can project a point to the screen.
export function cameraOf(scene) {
  return {
    projection: Cesium.Matrix4.toArray(scene.camera.frustum.projectionMatrix),
    view: Cesium.Matrix4.toArray(scene.camera.viewMatrix),
    width: scene.canvas.clientWidth,
    height: scene.canvas.clientHeight,
  };
}

/// Runs the page's `body` (async); an error goes to state.error (with its stack) and the console.
export function runPage(state, body) {
  body().catch((error) => {
    state.error = String(error && error.stack ? error.stack : error);
    console.error(error);
  });
}
