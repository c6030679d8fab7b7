// The VSM browser viewer: streams a model's OGC 3D Tiles view from vsmd with three.js and
// 3d-tiles-renderer.
//
//   /viewer/?model=ID[&mode=lod|texture][&view=oblique|top][&error=PIXELS][&tileset=URL]
//
// mode=lod (the default) colours every tile by its depth in the pyramid, the depth being the first
// number of its content URI "depth_x_y.glb", with the palette of `vsm render-lod`
// (core/tiles/README.md, kDepthPalette); mode=texture shows the GLB's own material: a textured
// tile unlit (the image's own colours, as imagery is shown), an untextured one lit by a headlight.
// view=top looks straight down on the model (north up) instead of from above and to the south.
// error is the screen-space error target in pixels (default 4; smaller loads deeper levels
// sooner).
//
// For tests and scripts, window.vsmViewer holds counters: tiles requested, loaded (of them
// textured) and failed, pending loads, `idle` (the root is in and nothing is queued, downloading
// or parsing), and `camera`: the matrices of the last frame drawn (column-major, as three.js keeps
// them) and the canvas size in CSS pixels, so that a script can project a point to the screen.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { TilesRenderer } from '3d-tiles-renderer';

/// sRGB colour per depth, 15 and deeper share the last: the same as kDepthPalette.
export const DEPTH_PALETTE = [
  '#30123b', '#4145ab', '#4675ed', '#39a2fc', '#1bcfd4', '#24eca6', '#61fc6c', '#a4fc3b',
  '#d1e834', '#f3c63a', '#fe9b2d', '#f36315', '#d93806', '#b11901', '#7a0402', '#4a0000',
];

const params = new URLSearchParams(window.location.search);
const modelId = params.get('model');
let mode = params.get('mode') === 'texture' ? 'texture' : 'lod';
const view = params.get('view') === 'top' ? 'top' : 'oblique';

const state = {
  model: modelId,
  mode,
  view,
  requested: 0,
  loaded: 0,
  textured: 0,
  failed: 0,
  errors: [],
  depths: {},
  rootLoaded: false,
  pending: 0,
  idle: false,
  frames: 0,
  camera: null,
};
window.vsmViewer = state;

const statusEl = document.getElementById('status');
function showStatus(text) {
  statusEl.textContent = text;
}

/// The depth of a tile from its content URL (".../3dtiles/2_1_3.glb" -> 2); null if it has none.
export function depthOf(url) {
  const match = /(?:^|\/)(\d+)_\d+_\d+\.glb(?:[?#].*)?$/.exec(url || '');
  return match ? Number(match[1]) : null;
}

function paletteColour(depth) {
  return DEPTH_PALETTE[Math.min(depth, DEPTH_PALETTE.length - 1)];
}

// The legend under the mode switch.
const legend = document.getElementById('legend');
DEPTH_PALETTE.forEach((colour, depth) => {
  const swatch = document.createElement('span');
  swatch.style.background = colour;
  swatch.title = depth === DEPTH_PALETTE.length - 1 ? `depth ${depth}+` : `depth ${depth}`;
  legend.appendChild(swatch);
});
for (const input of document.querySelectorAll('input[name=mode]')) {
  input.checked = input.value === mode;
  input.addEventListener('change', () => setMode(input.value));
}

if (!modelId) {
  showStatus('no model: open /viewer/?model=ID');
  throw new Error('no model given (?model=ID)');
}
document.getElementById('title').textContent = `VSM: ${modelId}`;
document.title = `VSM viewer: ${modelId}`;

// ---- scene ------------------------------------------------------------------------------------

const canvas = document.getElementById('view');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setSize(window.innerWidth, window.innerHeight, false);
renderer.setClearColor(0x101418);

const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(45, window.innerWidth / window.innerHeight, 1, 1e7);
const controls = new OrbitControls(camera, canvas);
controls.enableDamping = false;

// A light from the camera (it follows it) and a dim fill, for the texture mode's lit material.
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 0.8));
const headlight = new THREE.DirectionalLight(0xffffff, 1.6);
scene.add(headlight, headlight.target);

const tilesetUrl = params.get('tileset') ||
  new URL(`/v1/models/${encodeURIComponent(modelId)}/3dtiles/tileset.json`,
    window.location.href).toString();
const tiles = new TilesRenderer(tilesetUrl);
const errorTarget = Number(params.get('error'));
tiles.errorTarget = errorTarget > 0 ? errorTarget : 4;
tiles.setCamera(camera);
tiles.setResolutionFromRenderer(camera, renderer);
scene.add(tiles.group);

// ---- colouring --------------------------------------------------------------------------------

/// One unlit material per depth (the exact palette colour whatever the light) shared by its tiles.
const lodMaterials = new Map();
function lodMaterial(depth) {
  const key = Math.min(depth, DEPTH_PALETTE.length - 1);
  if (!lodMaterials.has(key)) {
    lodMaterials.set(key, new THREE.MeshBasicMaterial({
      color: new THREE.Color(paletteColour(key)),
      side: THREE.DoubleSide,
    }));
  }
  return lodMaterials.get(key);
}

/// The material a mesh shows in texture mode: its own, except that a textured one is drawn unlit
/// (a MeshBasicMaterial with the same image and colour, made once per mesh and disposed with it).
function textureMaterial(object) {
  const own = object.userData.vsmOwnMaterial;
  if (!own.map) {
    return own;
  }
  if (!object.userData.vsmUnlitMaterial) {
    object.userData.vsmUnlitMaterial = new THREE.MeshBasicMaterial({
      map: own.map,
      color: own.color,
      side: own.side,
      transparent: own.transparent,
      opacity: own.opacity,
    });
  }
  return object.userData.vsmUnlitMaterial;
}

function materialFor(object) {
  return mode === 'lod' && object.userData.vsmDepth !== null
    ? lodMaterial(object.userData.vsmDepth) : textureMaterial(object);
}

/// Keeps a tile's own material and depth on its meshes and shows it in the current mode; true if
/// any of its meshes carries a texture.
function colourTile(tileScene, depth) {
  let textured = false;
  tileScene.traverse((object) => {
    if (!object.isMesh) {
      return;
    }
    if (!object.userData.vsmOwnMaterial) {
      object.userData.vsmOwnMaterial = object.material;
      object.userData.vsmDepth = depth;
    }
    textured = textured || Boolean(object.userData.vsmOwnMaterial.map);
    object.material = materialFor(object);
  });
  return textured;
}

function setMode(next) {
  mode = next === 'texture' ? 'texture' : 'lod';
  state.mode = mode;
  tiles.group.traverse((object) => {
    if (object.isMesh && object.userData.vsmOwnMaterial) {
      object.material = materialFor(object);
    }
  });
  const url = new URL(window.location.href);
  url.searchParams.set('mode', mode);
  window.history.replaceState(null, '', url);
}

// ---- events and counters ----------------------------------------------------------------------

tiles.addEventListener('tile-download-start', () => {
  state.requested++;
});
tiles.addEventListener('load-model', ({ scene: tileScene, url }) => {
  const depth = depthOf(url);
  state.loaded++;
  if (depth !== null) {
    state.depths[depth] = (state.depths[depth] || 0) + 1;
  }
  if (colourTile(tileScene, depth)) {
    state.textured++;
  }
});
tiles.addEventListener('dispose-model', ({ scene: tileScene }) => {
  tileScene.traverse((object) => {
    if (object.isMesh && object.userData.vsmOwnMaterial) {
      object.material = object.userData.vsmOwnMaterial;  // disposed by the renderer, not ours
      if (object.userData.vsmUnlitMaterial) {
        object.userData.vsmUnlitMaterial.dispose();  // ours; the image is the renderer's
        delete object.userData.vsmUnlitMaterial;
      }
    }
  });
});
tiles.addEventListener('load-error', ({ url, error }) => {
  state.failed++;
  state.errors.push(`${url}: ${error && error.message ? error.message : error}`);
});

let placed = false;
/// Looks at the tileset's bounding volume from above and to the south (view=top: straight down,
/// north up, the bounding sphere filling the view), once the root is in.
function placeCamera() {
  const sphere = new THREE.Sphere();
  if (!tiles.getBoundingSphere(sphere)) {
    return false;
  }
  const centre = sphere.center.clone().applyMatrix4(tiles.group.matrixWorld);
  const radius = Math.max(sphere.radius, 1);
  // ECEF: "up" is away from the earth's centre (a local tileset without one looks along +z).
  const up = centre.lengthSq() > 1e10 ? centre.clone().normalize() : new THREE.Vector3(0, 0, 1);
  const north = new THREE.Vector3(0, 0, 1).sub(up.clone().multiplyScalar(up.z));
  if (north.lengthSq() < 1e-8) {
    north.set(0, 1, 0);
  }
  north.normalize();
  camera.up.copy(up);  // the orbit's axis
  if (view === 'top') {
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
  return true;
}

function onResize() {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight, false);
  tiles.setResolutionFromRenderer(camera, renderer);
}
window.addEventListener('resize', onResize);

function frame() {
  requestAnimationFrame(frame);
  if (!placed) {
    placed = placeCamera();
  }
  camera.updateMatrixWorld();
  tiles.update();
  headlight.position.copy(camera.position);
  headlight.target.position.copy(controls.target);
  renderer.render(scene, camera);
  state.camera = {
    projection: camera.projectionMatrix.toArray(),
    view: camera.matrixWorldInverse.toArray(),
    world: tiles.group.matrixWorld.toArray(),
    width: canvas.clientWidth,
    height: canvas.clientHeight,
  };

  const stats = tiles.stats;
  state.rootLoaded = placed;
  state.pending = stats.queued + stats.downloading + stats.parsing;
  state.idle = placed && state.pending === 0 && !tiles.isLoading;
  state.frames++;
  showStatus(`${mode === 'lod' ? 'level of detail' : 'texture'}: ${state.loaded} tiles` +
    (state.pending ? `, ${state.pending} loading` : '') +
    (state.failed ? `, ${state.failed} FAILED` : ''));
}
frame();
