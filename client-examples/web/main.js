// The VSM browser viewer: streams a model's OGC 3D Tiles view from vsmd with three.js and
// 3d-tiles-renderer.
//
//   /viewer/?model=ID[&mode=lod|relief|texture][&lit=1][&view=oblique|top][&error=PIXELS]
//            [&exaggeration=K][&sun=AZIMUTH,ALTITUDE][&fly=ID][&merge=ID][&tileset=URL]
//
// mode=lod (the default) colours every tile by its depth in the pyramid, the depth being the first
// number of its content URI "depth_x_y.glb", with the palette of `vsm render-lod`
// (core/tiles/README.md, kDepthPalette); mode=relief shades the surface in grey by the sun;
// mode=texture shows the GLB's image (an untextured tile as in relief). lod and texture are unlit
// (exact palette colours, the image's own colours, as imagery is shown) unless lit=1.
//
// The sun: azimuth (degrees clockwise from north) and altitude (degrees above the horizon) in each
// point's own east-north-up frame, as a hillshade has it (one fixed direction would light a model
// the size of the US differently in the east and the west); default 315,45, GDAL's. A surface
// facing it is lit fully, one facing away gets AMBIENT. Normals are the GLB's when it has them,
// otherwise computed per tile from its triangles.
// exaggeration scales every vertex's height above the WGS 84 ellipsoid (default 1).
// view=top looks straight down on the model (north up) instead of from above and to the south.
// error is the screen-space error target in pixels (default 4; smaller loads deeper levels sooner).
// fly=ID flies to the finest area (the deepest level's bounds) of model ID once the model is in.
// merge=ID preselects ID as the model the merge button merges into the shown one.
// mode=changes colours each tile by its displacement between revision from=A (default: the one
// before the shown revision) and the shown one (GET /v1/models/{m}/diff): the patch's largest
// signed displacement over the range of the whole diff, blue (down) - white (unchanged) - red (up);
// tiles the two revisions share are white.
// rev=N shows kept revision N of the model (GET /v1/models/{m}/revisions; the picker lists them)
// instead of the latest; a publish then changes nothing on screen but the picker.
//
// Live: the page follows GET /v1/events. Job progress is shown; on a `published` event for the
// shown model it replaces the tileset by the new version's (tile URIs carry patch versions: the
// browser's cache answers the unchanged tiles) and reads the model's levels again (legend,
// fly-to).
//
// For tests and scripts, window.vsmViewer holds counters of the tileset drawn: tiles requested,
// loaded (of them textured) and failed, pending loads, `idle` (the root is in and nothing is
// queued, downloading or parsing), `version` (the model version drawn),
// `revision` (the revision picked, null for the latest), `revisions` (the kept ones listed),
// `changes` (from, to, range in metres, patches of the diff, or error), `shown[].change` (in
// changes mode, the displacement a drawn tile is coloured by), `reloads`, `frames` (frames
// drawn: the page draws only when what it shows changed), `shown` (key, depth and ECEF box of
// each tile drawn), `legend`, `jobs`, `published`, `overlays` (screen rectangles of the panel
// and legend) and `camera`: the matrices of the last frame drawn (column-major, as three.js keeps
// them) and the canvas size in CSS pixels, so that a script can project a point to the screen.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { MeshoptDecoder } from 'three/addons/libs/meshopt_decoder.module.js';
import { TilesRenderer } from '3d-tiles-renderer';

/// sRGB colour per depth, 15 and deeper share the last: the same as kDepthPalette.
export const DEPTH_PALETTE = [
  '#30123b', '#4145ab', '#4675ed', '#39a2fc', '#1bcfd4', '#24eca6', '#61fc6c', '#a4fc3b',
  '#d1e834', '#f3c63a', '#fe9b2d', '#f36315', '#d93806', '#b11901', '#7a0402', '#4a0000',
];
/// The relief's grey (sRGB) and the share of it a surface facing away from the sun keeps.
const RELIEF_GREY = '#c8c8c8';
const AMBIENT = 0.2;
const DEFAULT_SUN = [315, 45];
const MODES = ['lod', 'relief', 'texture', 'changes'];
const MODE_NAMES = {
  lod: 'level of detail', relief: 'relief', texture: 'texture', changes: 'changes',
};
/// The diverging scale of the changes mode (sRGB): blue below, white unchanged, red above.
const CHANGE_LOW = [0x21, 0x66, 0xac];
const CHANGE_HIGH = [0xb2, 0x18, 0x2b];
const CHANGE_BINS = 10;
// WGS 84.
const WGS84_A = 6378137.0;
const WGS84_B = 6356752.314245179;

const params = new URLSearchParams(window.location.search);
const modelId = params.get('model');
let mode = MODES.includes(params.get('mode')) ? params.get('mode') : 'lod';
let lit = params.get('lit') === '1';
const view = params.get('view') === 'top' ? 'top' : 'oblique';
const sunParam = (params.get('sun') || '').split(',').map(Number);
const sun = sunParam.length === 2 && sunParam.every(Number.isFinite) ? sunParam : DEFAULT_SUN;
let exaggeration = Math.max(Number(params.get('exaggeration')) || 1, 0);
/// The revision shown; null: the latest, following publishes.
let revision = Number.isInteger(Number(params.get('rev'))) && Number(params.get('rev')) > 0
  ? Number(params.get('rev')) : null;

/// The counters of one tileset's renderer (the drawn one's are copied into window.vsmViewer).
function newCounts() {
  return { requested: 0, loaded: 0, textured: 0, failed: 0, errors: [], depths: {} };
}

const state = {
  model: modelId,
  mode,
  lit,
  view,
  sun: { azimuth: sun[0], altitude: sun[1] },
  exaggeration,
  ...newCounts(),
  rootLoaded: false,
  pending: 0,
  idle: false,
  frames: 0,
  version: null,
  revision,
  revisions: [],
  changes: null,
  reloads: 0,
  shown: [],
  legend: [],
  jobs: {},
  published: [],
  flownTo: null,
  overlays: [],
  camera: null,
};
window.vsmViewer = state;

const $ = (id) => document.getElementById(id);
function showStatus(text) {
  $('status').textContent = text;
}

/// The depth of a tile from its content URL (".../3dtiles/2_1_3.glb" -> 2); null if it has none.
export function depthOf(url) {
  const match = /(?:^|\/)(\d+)_\d+_\d+\.glb(?:[?#].*)?$/.exec(url || '');
  return match ? Number(match[1]) : null;
}

/// The patch key of a tile from its content URL (".../2_1_3.glb?v=4" -> "2_1_3"); null if none.
function keyOf(url) {
  const match = /(?:^|\/)(\d+_\d+_\d+)\.glb(?:[?#].*)?$/.exec(url || '');
  return match ? match[1] : null;
}

function paletteColour(depth) {
  return DEPTH_PALETTE[Math.min(depth, DEPTH_PALETTE.length - 1)];
}

/// "4.6 km", "37 m", "2.5 m", "0.80 m", "3.2 cm", "4.0 mm": within 5 % of the value from 1 mm up,
/// and never "0.0 m" for a fine level of a rock-face scan.
function formatMetres(metres) {
  if (metres === null || metres === undefined) {
    return 'n/a';
  }
  const size = Math.abs(metres);
  if (size >= 1000) {
    return `${(metres / 1000).toFixed(size >= 10000 ? 0 : 1)} km`;
  }
  if (size >= 0.1 || size === 0) {
    return `${metres.toFixed(size >= 10 ? 0 : size >= 1 ? 1 : 2)} m`;
  }
  if (size >= 0.01) {
    return `${(metres * 100).toFixed(1)} cm`;
  }
  return `${(metres * 1000).toFixed(size >= 0.001 ? 1 : 2)} mm`;
}

async function getJson(path) {
  const response = await fetch(path, { cache: 'no-store' });
  if (!response.ok) {
    throw new Error(`GET ${path}: ${response.status}`);
  }
  return response.json();
}

// ---- controls ---------------------------------------------------------------------------------

for (const input of document.querySelectorAll('input[name=mode]')) {
  input.checked = input.value === mode;
  input.addEventListener('change', () => setMode(input.value));
}
$('lit').checked = lit;
$('lit').addEventListener('change', () => {
  lit = $('lit').checked;
  state.lit = lit;
  recolour();
});
$('exaggeration').value = String(exaggeration);
$('exaggeration-value').textContent = `${exaggeration}x`;
$('exaggeration').addEventListener('input', () => setExaggeration(Number($('exaggeration').value)));

if (!modelId) {
  showStatus('no model: open /viewer/?model=ID');
  throw new Error('no model given (?model=ID)');
}
$('title').textContent = `VSM: ${modelId}`;
document.title = `VSM viewer: ${modelId}`;

/// Keeps the URL in step with the controls, so that a reload or a shared link shows the same.
function setParam(name, value, fallback) {
  const url = new URL(window.location.href);
  if (value === fallback) {
    url.searchParams.delete(name);
  } else {
    url.searchParams.set(name, value);
  }
  window.history.replaceState(null, '', url);
}

// ---- scene ------------------------------------------------------------------------------------

const canvas = $('view');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio);
renderer.setSize(window.innerWidth, window.innerHeight, false);
renderer.setClearColor(0x101418);

const scene = new THREE.Scene();
const camera = new THREE.PerspectiveCamera(45, window.innerWidth / window.innerHeight, 1, 1e7);
const controls = new OrbitControls(camera, canvas);
controls.enableDamping = false;

/// The page draws a frame only when what it shows changed: frame() compares the camera with the
/// one last drawn (orbit controls, fly-to), and whatever else changes the picture (a tile came,
/// went or changed visibility, a control changed the materials or the shapes, a resize) calls
/// invalidate(). An idle page then costs no rendering (with a software renderer a frame of fine
/// tiles takes about a second).
let needsFrame = true;
function invalidate() {
  needsFrame = true;
}

const errorTarget = Number(params.get('error'));
const tilesetBase = params.get('tileset') ||
  new URL(`/v1/models/${encodeURIComponent(modelId)}/3dtiles/tileset.json`,
    window.location.href).toString();

// ---- shading ----------------------------------------------------------------------------------

/// The sun as a uniform all lit materials share (radians: azimuth, altitude).
const sunUniform = { value: new THREE.Vector2() };
function setSun(azimuth, altitude) {
  sunUniform.value.set(THREE.MathUtils.degToRad(azimuth), THREE.MathUtils.degToRad(altitude));
  state.sun = { azimuth, altitude };
  invalidate();
}
setSun(sun[0], sun[1]);

const SUN_VERTEX = `
varying vec3 vNormal;
varying vec3 vWorld;
#ifdef VSM_MAP
varying vec2 vUv;
#endif
void main() {
  vWorld = (modelMatrix * vec4(position, 1.0)).xyz;
  vNormal = mat3(modelMatrix) * normal;
#ifdef VSM_MAP
  vUv = uv;
#endif
  gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
}`;

// Up is the geocentric direction (within 0.2 degrees of the ellipsoid's normal), east and north
// follow from it; normals are turned to face up (a terrain's triangles may wind either way).
const SUN_FRAGMENT = `
uniform vec3 colour;
uniform vec2 sun;
uniform float ambient;
#ifdef VSM_MAP
uniform sampler2D map;
varying vec2 vUv;
#endif
varying vec3 vNormal;
varying vec3 vWorld;
void main() {
  vec3 up = normalize(vWorld);
  vec3 east = normalize(vec3(-up.y, up.x, 0.0));
  vec3 north = cross(up, east);
  vec3 light = cos(sun.y) * (sin(sun.x) * east + cos(sun.x) * north) + sin(sun.y) * up;
  vec3 n = normalize(vNormal);
  n = dot(n, up) < 0.0 ? -n : n;
  float shade = ambient + (1.0 - ambient) * max(dot(n, light), 0.0);
  vec4 c = vec4(colour, 1.0);
#ifdef VSM_MAP
  c *= texture2D(map, vUv);
#endif
  gl_FragColor = vec4(c.rgb * shade, c.a);
  #include <colorspace_fragment>
}`;

/// A material lit by the sun: `colour` (sRGB), times `map` when given.
function sunMaterial(colour, map = null) {
  return new THREE.ShaderMaterial({
    uniforms: {
      colour: { value: new THREE.Color(colour) },
      sun: sunUniform,
      ambient: { value: AMBIENT },
      map: { value: map },
    },
    defines: map ? { VSM_MAP: '' } : {},
    vertexShader: SUN_VERTEX,
    fragmentShader: SUN_FRAGMENT,
    side: THREE.DoubleSide,
  });
}

const reliefMaterial = sunMaterial(RELIEF_GREY);

/// Materials per depth shared by its tiles: unlit (the exact palette colour) and lit.
const lodMaterials = new Map();
function lodMaterial(depth) {
  const key = `${Math.min(depth, DEPTH_PALETTE.length - 1)}${lit ? 'lit' : ''}`;
  if (!lodMaterials.has(key)) {
    lodMaterials.set(key, lit ? sunMaterial(paletteColour(depth)) : new THREE.MeshBasicMaterial({
      color: new THREE.Color(paletteColour(depth)),
      side: THREE.DoubleSide,
    }));
  }
  return lodMaterials.get(key);
}

/// The material a textured mesh shows in texture mode, made once per mesh and disposed with it:
/// unlit (a MeshBasicMaterial with the image and colour of its own) or lit by the sun.
function textureMaterial(object) {
  const own = object.userData.vsmOwnMaterial;
  const key = lit ? 'vsmLitMaterial' : 'vsmUnlitMaterial';
  if (!object.userData[key]) {
    object.userData[key] = lit ? sunMaterial('#ffffff', own.map) : new THREE.MeshBasicMaterial({
      map: own.map,
      color: own.color,
      side: own.side,
      transparent: own.transparent,
      opacity: own.opacity,
    });
  }
  return object.userData[key];
}

/// The displacements of the changes mode: {from, to, range, values: key -> signed metres}.
let changes = null;
const changeMaterials = new Map();
function changeColour(t) {
  const end = t < 0 ? CHANGE_LOW : CHANGE_HIGH;
  const a = Math.abs(t);
  return new THREE.Color(...end.map((c) => (255 + (c - 255) * a) / 255)).convertSRGBToLinear();
}
function changeMaterial(value) {
  const t = changes && changes.range > 0 ? Math.max(-1, Math.min(1, value / changes.range)) : 0;
  const bin = Math.round(t * CHANGE_BINS);
  const key = `${bin}${lit ? 'lit' : ''}`;
  if (!changeMaterials.has(key)) {
    const colour = changeColour(bin / CHANGE_BINS);
    changeMaterials.set(key, lit ? sunMaterial(`#${colour.getHexString()}`)
      : new THREE.MeshBasicMaterial({ color: colour, side: THREE.DoubleSide }));
  }
  return changeMaterials.get(key);
}
function changeOf(key) {
  return changes ? changes.values.get(key) || 0 : 0;
}

/// Reads the diff the changes mode shows: from ?from= or the kept revision before the shown one,
/// to the shown one.
async function readChanges(latest = latestRevision()) {
  const to = revision !== null ? revision : latest;
  const earlier = state.revisions.map((r) => r.revision).filter((n) => n < to);
  const from = Number(params.get('from')) || earlier[earlier.length - 1];
  if (!from || !to) {
    state.changes = { error: 'no earlier revision to compare with' };
    return;
  }
  const diff = await getJson(
    `/v1/models/${encodeURIComponent(modelId)}/diff?from=${from}&to=${to}`);
  const values = new Map();
  for (const p of diff.patches) {
    if (p.max_abs !== null) {
      values.set(p.key, Math.abs(p.max) >= Math.abs(p.min) ? p.max : p.min);
    }
  }
  changes = { from, to, range: diff.totals.max_abs || 0, values };
  state.changes = { from, to, range: changes.range, patches: values.size };
  const legend = $('changes-legend');
  const low = `#${changeColour(-1).convertLinearToSRGB().getHexString()}`;
  const high = `#${changeColour(1).convertLinearToSRGB().getHexString()}`;
  legend.textContent = `changes ${from} -> ${to}: ${formatMetres(-changes.range)} `;
  const bar = document.createElement('span');
  bar.className = 'bar';
  bar.style.background = `linear-gradient(to right, ${low}, #ffffff, ${high})`;
  legend.append(bar, ` ${formatMetres(changes.range)}`);
  recolour();
}

function materialFor(object) {
  if (mode === 'changes') {
    return changeMaterial(changeOf(object.userData.vsmKey));
  }
  if (mode === 'lod' && object.userData.vsmDepth !== null) {
    return lodMaterial(object.userData.vsmDepth);
  }
  return mode === 'texture' && object.userData.vsmOwnMaterial.map
    ? textureMaterial(object) : reliefMaterial;
}

function recolour() {
  tiles.group.traverse((object) => {
    if (object.isMesh && object.userData.vsmOwnMaterial) {
      object.material = materialFor(object);
    }
  });
  setParam('lit', lit ? '1' : '0', '0');
  invalidate();
}

function setMode(next) {
  mode = MODES.includes(next) ? next : 'lod';
  state.mode = mode;
  $('changes-legend').hidden = mode !== 'changes';
  if (mode === 'changes') {
    readChanges().catch((error) => {
      state.changes = { error: String(error) };
    });
  }
  recolour();
  setParam('mode', mode, 'lod');
}

// ---- vertical exaggeration and normals --------------------------------------------------------

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
/// has them, else computed) and bounds.
function shapeMesh(mesh) {
  const geometry = mesh.geometry;
  const data = mesh.userData;
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

function setExaggeration(k) {
  exaggeration = Math.max(k, 0);
  state.exaggeration = exaggeration;
  $('exaggeration-value').textContent = `${exaggeration}x`;
  tiles.group.traverse((object) => {
    if (object.isMesh && object.userData.vsmOriginal) {
      shapeMesh(object);
    }
  });
  setParam('exaggeration', String(exaggeration), '1');
  invalidate();
}

// ---- tilesets ---------------------------------------------------------------------------------

/// The ECEF axis-aligned box of a tile's bounding box (centre and half axes in its frame).
function tileBox(tile) {
  const b = tile.boundingVolume && tile.boundingVolume.box;
  const transform = tile.engineData && tile.engineData.transform;
  if (!b || !transform) {
    return null;
  }
  const box = new THREE.Box3();
  for (const sx of [-1, 1]) {
    for (const sy of [-1, 1]) {
      for (const sz of [-1, 1]) {
        const corner = new THREE.Vector3(
          b[0] + sx * b[3] + sy * b[6] + sz * b[9],
          b[1] + sx * b[4] + sy * b[7] + sz * b[10],
          b[2] + sx * b[5] + sy * b[8] + sz * b[11]);
        box.expandByPoint(corner.applyMatrix4(transform));
      }
    }
  }
  return { min: box.min.toArray(), max: box.max.toArray() };
}

/// A renderer of one version of the tileset, with its own counters (`t.vsmCounts`) and the tiles
/// it shows (`t.vsmShown`: tile -> {key, depth, box}).
function makeTiles(url) {
  const t = new TilesRenderer(url);
  // vsmd's tiles are KHR_mesh_quantization + EXT_meshopt_compression GLBs (the default): the
  // renderer takes its glTF loader from the manager's handler for "path.glb", so register one
  // that decodes meshopt (WebAssembly, in meshopt_decoder.module.js).
  const gltfLoader = new GLTFLoader(t.manager);
  gltfLoader.setMeshoptDecoder(MeshoptDecoder);
  t.manager.addHandler(/\.(gltf|glb)$/, gltfLoader);
  t.errorTarget = errorTarget > 0 ? errorTarget : 4;
  t.setCamera(camera);
  t.setResolutionFromRenderer(camera, renderer);
  const counts = newCounts();
  t.vsmCounts = counts;
  t.vsmShown = new Map();
  for (const type of ['needs-render', 'needs-update', 'load-model', 'dispose-model',
    'tile-visibility-change']) {
    t.addEventListener(type, invalidate);
  }
  t.addEventListener('tile-download-start', () => {
    counts.requested++;
  });
  t.addEventListener('load-model', ({ scene: tileScene, url: tileUrl }) => {
    const depth = depthOf(tileUrl);
    counts.loaded++;
    if (depth !== null) {
      counts.depths[depth] = (counts.depths[depth] || 0) + 1;
    }
    // Not in the group yet: its matrices are its tile's transform (group frame = ECEF).
    tileScene.updateMatrixWorld(true);
    let textured = false;
    tileScene.traverse((object) => {
      if (!object.isMesh) {
        return;
      }
      object.userData.vsmOwnMaterial = object.material;
      object.userData.vsmDepth = depth;
      object.userData.vsmKey = keyOf(tileUrl);
      object.userData.vsmToEcef = object.matrixWorld.clone();
      textured = textured || Boolean(object.material.map);
      shapeMesh(object);
      object.material = materialFor(object);
    });
    if (textured) {
      counts.textured++;
    }
  });
  t.addEventListener('tile-visibility-change', ({ tile, visible }) => {
    const tileUrl = tile.content && tile.content.uri;
    if (visible && tileUrl) {
      t.vsmShown.set(tile, { key: keyOf(tileUrl), depth: depthOf(tileUrl), box: tileBox(tile) });
    } else {
      t.vsmShown.delete(tile);
    }
  });
  t.addEventListener('dispose-model', ({ scene: tileScene }) => {
    tileScene.traverse((object) => {
      if (object.isMesh && object.userData.vsmOwnMaterial) {
        object.material = object.userData.vsmOwnMaterial;  // disposed by the renderer, not ours
        for (const key of ['vsmUnlitMaterial', 'vsmLitMaterial']) {
          if (object.userData[key]) {
            object.userData[key].dispose();  // ours; the image is the renderer's
            delete object.userData[key];
          }
        }
      }
    });
  });
  t.addEventListener('load-error', ({ url: tileUrl, error }) => {
    counts.failed++;
    counts.errors.push(`${tileUrl}: ${error && error.message ? error.message : error}`);
  });
  return t;
}

/// The tileset of the revision shown: `rev=N` for a picked one (its tiles' URIs carry it too),
/// else the latest, `v=` naming the version so that no cache answers an older one.
function tilesetUrl(version) {
  const url = new URL(tilesetBase);
  if (revision !== null) {
    url.searchParams.set('rev', String(revision));
  } else if (version !== null) {
    url.searchParams.set('v', String(version));
  }
  return url.toString();
}

let tiles = makeTiles(tilesetUrl(null));
scene.add(tiles.group);

/// Replaces the tileset by model version `version`'s (the URL names it, so no cache answers the
/// old one), or by the picked revision's. Unchanged tiles keep their URIs, so the browser's cache
/// answers them; the changed ones load anew. (Loading the new version beside the old one and
/// swapping when it is complete would avoid the moment of coarser tiles, but 3d-tiles-renderer's
/// renderers share one tile cache and queues, and the second one starved.)
function reloadTileset(version) {
  scene.remove(tiles.group);
  tiles.dispose();
  tiles = makeTiles(tilesetUrl(version));
  scene.add(tiles.group);
  invalidate();
  state.version = revision !== null ? revision : version;
  state.reloads++;
  state.idle = false;
  if (mode === 'changes') {
    changes = null;
    state.changes = null;
    readChanges(version).catch((error) => {
      state.changes = { error: String(error) };
    });
  }
}

/// The revision picker: the latest (followed as it is published) and each kept revision, with
/// when and by which job it was made.
async function readRevisions() {
  const list = (await getJson(`/v1/models/${encodeURIComponent(modelId)}/revisions`)).revisions;
  state.revisions = list.map((r) => ({ revision: r.revision, time: r.time, job: r.job,
    latest: r.latest }));
  const select = $('revision');
  select.textContent = '';
  const latest = document.createElement('option');
  latest.value = '';
  latest.textContent = 'latest';
  select.appendChild(latest);
  for (const r of [...list].reverse()) {
    const option = document.createElement('option');
    option.value = String(r.revision);
    option.textContent = `${r.revision}${r.latest ? ' (latest)' : ''} ${r.time.slice(0, 16)}` +
      (r.restored_from ? ` restores ${r.restored_from}` : '');
    select.appendChild(option);
  }
  select.value = revision === null ? '' : String(revision);
}

/// The newest revision listed (the model's version), else the version drawn.
function latestRevision() {
  const latest = state.revisions.find((r) => r.latest);
  return latest ? latest.revision : state.version;
}

function pickRevision(value) {
  revision = value ? Number(value) : null;
  state.revision = revision;
  setParam('rev', revision === null ? '' : String(revision), '');
  reloadTileset(latestRevision());
  readModel().catch((error) => console.warn(error));
}

// ---- the model: legend, fly-to, merge ---------------------------------------------------------

/// Fills the legend from the model's levels (GET /v1/models/{m}): each depth's palette colour and
/// resolution (mean distance between grid neighbours).
async function readModel() {
  const info = await getJson(`/v1/models/${encodeURIComponent(modelId)}` +
    (revision !== null ? `?rev=${revision}` : ''));
  if (state.version === null) {
    state.version = info.version;
  }
  const legend = $('legend');
  legend.textContent = '';
  state.legend = info.levels.map((level) => {
    const entry = document.createElement('span');
    entry.className = 'entry';
    entry.dataset.depth = String(level.depth);
    const swatch = document.createElement('span');
    swatch.className = 'swatch';
    swatch.style.background = paletteColour(level.depth);
    entry.append(swatch, `depth ${level.depth}: ${formatMetres(level.resolution)}`);
    legend.appendChild(entry);
    const r = swatch.getBoundingClientRect();
    return {
      depth: level.depth,
      resolution: level.resolution,
      colour: paletteColour(level.depth),
      text: entry.textContent,
      swatch: { x: r.x, y: r.y, width: r.width, height: r.height },
    };
  });
  return info;
}

/// The finest area of each open model (its deepest level's bounds) as fly-to buttons, and the
/// other models as merge sources.
const finest = new Map();
async function readModels() {
  const list = await getJson('/v1/models');
  const fly = $('fly');
  fly.textContent = 'fly to: ';
  const select = $('merge-source');
  const wanted = select.value || params.get('merge');
  select.textContent = '';
  for (const entry of list.models) {
    const info = await getJson(`/v1/models/${encodeURIComponent(entry.id)}`);
    const deepest = info.levels[info.levels.length - 1];
    if (deepest && deepest.bounds) {
      finest.set(entry.id, deepest.bounds);
      const button = document.createElement('button');
      button.dataset.model = entry.id;
      button.textContent = entry.id;
      button.title = `the finest area of ${entry.id}: depth ${deepest.depth}, ` +
        `${formatMetres(deepest.resolution)}`;
      button.addEventListener('click', () => flyTo(entry.id));
      fly.appendChild(button);
    }
    if (entry.id !== modelId) {
      const option = document.createElement('option');
      option.value = entry.id;
      option.textContent = entry.id;
      option.selected = entry.id === wanted;
      select.appendChild(option);
    }
  }
  $('merge-row').hidden = select.options.length === 0;
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
}

function flyTo(id) {
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

let placed = false;
/// Looks at the tileset's bounding volume once the root is in.
function placeCamera() {
  const sphere = new THREE.Sphere();
  if (!tiles.getBoundingSphere(sphere)) {
    return false;
  }
  lookAt(sphere.center.clone().applyMatrix4(tiles.group.matrixWorld), Math.max(sphere.radius, 1));
  return true;
}

/// POST /v1/jobs: merges the selected model into the shown one. A daemon with a token answers 401:
/// then the page asks for the token once and keeps it for the tab (sessionStorage).
async function submitMerge() {
  const source = $('merge-source').value;
  const body = JSON.stringify({ type: 'merge', target: modelId, source });
  for (let attempt = 0; attempt < 2; attempt++) {
    const headers = { 'Content-Type': 'application/json' };
    const token = sessionStorage.getItem('vsmToken');
    if (token) {
      headers.Authorization = `Bearer ${token}`;
    }
    const response = await fetch('/v1/jobs', { method: 'POST', headers, body });
    if (response.status === 401 && attempt === 0) {
      const entered = window.prompt('This vsmd needs a token for writes (vsmd --token):');
      if (!entered) {
        break;
      }
      sessionStorage.setItem('vsmToken', entered);
      continue;
    }
    const answer = await response.json().catch(() => ({}));
    if (!response.ok) {
      const message = answer.error ? answer.error.message : response.statusText;
      $('jobs').textContent = `merge refused: ${response.status} ${message}`;
      return;
    }
    state.jobs[answer.id] = {
      type: 'merge', state: answer.state, progress: 0, models: [modelId, source],
    };
    showJobs();
    return;
  }
  $('jobs').textContent = 'merge not submitted: no token';
}
$('merge').addEventListener('click', () => {
  submitMerge().catch((error) => {
    $('jobs').textContent = `merge failed: ${error.message}`;
  });
});

// ---- live events ------------------------------------------------------------------------------

function showJobs() {
  const lines = Object.entries(state.jobs).slice(-3).map(([id, job]) => {
    const what = `${job.type} ${job.models.join(' / ')}`;
    const how = job.state === 'running'
      ? `${Math.round(100 * job.progress)} %${job.stage ? ` (${job.stage})` : ''}`
      : job.state + (job.error ? `: ${job.error}` : '');
    return `${id}: ${what}: ${how}`;
  });
  $('jobs').textContent = lines.join('\n');
}

function followEvents() {
  const events = new EventSource('/v1/events');
  const onJob = (message) => {
    const data = JSON.parse(message.data);
    state.jobs[data.job] = {
      type: data.type,
      models: data.models,
      state: data.state,
      stage: data.stage,
      progress: data.progress === undefined ? 1 : data.progress,
      error: data.error ? data.error.message : null,
    };
    showJobs();
  };
  events.addEventListener('job', onJob);
  events.addEventListener('job_end', onJob);
  events.addEventListener('published', (message) => {
    const data = JSON.parse(message.data);
    state.published.push({ model: data.model, version: data.version,
      changed: data.changed_count });
    readModels().catch((error) => console.warn(error));
    if (data.model === modelId) {
      readRevisions().catch((error) => console.warn(error));
      if (revision === null) {
        reloadTileset(data.version);
        readModel().catch((error) => console.warn(error));
      }
    }
  });
}

$('changes-legend').hidden = mode !== 'changes';
Promise.all([readModel(), readRevisions()]).then(() => {
  if (mode === 'changes' && changes === null) {
    return readChanges();
  }
  return null;
}).catch((error) => console.warn(error));
$('revision').addEventListener('change', (event) => pickRevision(event.target.value));
let flyPending = params.get('fly');
readModels().then(() => {
  if (flyPending && placed) {
    flyTo(flyPending);
    flyPending = null;
  }
}).catch((error) => console.warn(error));
followEvents();

// ---- frames -----------------------------------------------------------------------------------

function onResize() {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight, false);
  tiles.setResolutionFromRenderer(camera, renderer);
  invalidate();
}
window.addEventListener('resize', onResize);

function rect(element) {
  const r = element.getBoundingClientRect();
  return { x: r.x, y: r.y, width: r.width, height: r.height };
}

const drawnView = new THREE.Matrix4();
const drawnProjection = new THREE.Matrix4();

function frame() {
  requestAnimationFrame(frame);
  if (!placed) {
    placed = placeCamera();
    if (placed && flyPending && finest.has(flyPending)) {
      flyTo(flyPending);
      flyPending = null;
    }
  }
  camera.updateMatrixWorld();
  tiles.update();
  if (needsFrame || !drawnView.equals(camera.matrixWorld) ||
      !drawnProjection.equals(camera.projectionMatrix)) {
    needsFrame = false;
    drawnView.copy(camera.matrixWorld);
    drawnProjection.copy(camera.projectionMatrix);
    renderer.render(scene, camera);
    state.frames++;
  }
  state.camera = {
    projection: camera.projectionMatrix.toArray(),
    view: camera.matrixWorldInverse.toArray(),
    world: tiles.group.matrixWorld.toArray(),
    width: canvas.clientWidth,
    height: canvas.clientHeight,
  };

  Object.assign(state, tiles.vsmCounts);
  state.shown = [...tiles.vsmShown.values()].map(
    (shown) => (mode === 'changes' ? { ...shown, change: changeOf(shown.key) } : shown));
  const stats = tiles.stats;
  state.rootLoaded = placed;
  state.pending = stats.queued + stats.downloading + stats.parsing;
  state.idle = placed && state.pending === 0 && !tiles.isLoading && flyPending === null;
  state.overlays = [rect($('panel')), rect($('legend'))];
  showStatus(`${MODE_NAMES[mode]}${lit || mode === 'relief' ? ', sun' : ''}: ` +
    `${state.loaded} tiles` +
    (state.pending ? `, ${state.pending} loading` : '') +
    (state.failed ? `, ${state.failed} FAILED` : ''));
}
frame();
