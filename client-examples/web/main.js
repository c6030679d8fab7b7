// The VSM browser viewer: streams a model's OGC 3D Tiles view from vsmd with three.js and
// 3d-tiles-renderer.
//
//   /viewer/?model=ID[&mode=lod|relief|texture][&lit=1][&view=oblique|top][&error=PIXELS]
//            [&exaggeration=K][&sun=AZIMUTH,ALTITUDE][&fly=ID][&merge=ID][&tileset=URL]
//            [&eye=X,Y,Z&at=X,Y,Z]
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
// eye and at place the camera at eye looking at at (the model's coordinates, metres) instead.
// A model in a local frame (not earth-centred: a tunnel, a rock face) gets a free-flying camera
// that can go inside it, its near plane tied to the model's finest resolution (js/camera.js), up
// along the frame's +z for the sun, and no height control.
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
// One concern a module, in js/ (native ES modules, no bundler): settings.js (the URL and this
// state), tileset.js (3d-tiles-renderer, one per version shown), materials.js and shading.js
// (the modes and the sun), exaggeration.js, changes.js (the diff), legend.js, models.js (fly-to
// and merge sources), revisions.js, camera.js, controls.js (the panel), jobs.js and events.js
// (live), and frames.js (draw only on change). This file puts them together and runs the frame
// loop.
//
// For tests and scripts, window.vsmViewer holds counters of the tileset drawn: tiles requested,
// loaded (of them textured) and failed, pending loads, `idle` (the root is in and nothing is
// queued, downloading or parsing), `version` (the model version drawn),
// `revision` (the revision picked, null for the latest), `revisions` (the kept ones listed),
// `changes` (from, to, range in metres, patches of the diff, or error), `shown[].change` (in
// changes mode, the displacement a drawn tile is coloured by), `reloads`, `frames` (frames
// drawn: the page draws only when what it shows changed), `shown` (key, depth and ECEF box of
// each tile drawn), `legend`, `jobs`, `published`, `overlays` (screen rectangles of the panel
// and legend), `frame` ('earth' or 'local', once the root is in), `near` (the camera's near plane,
// metres) and `camera`: the matrices of the last frame drawn (column-major, as three.js keeps
// them) and the canvas size in CSS pixels, so that a script can project a point to the screen.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { $, MODE_NAMES, modelId, params, state } from './js/settings.js';
import { drawIfChanged, invalidate } from './js/frames.js';
import { setEarthCentred, setSun } from './js/shading.js';
import { changeOf, haveChanges } from './js/changes.js';
import { currentTiles, startTiles } from './js/tileset.js';
import {
  adaptToFrame, initControls, initRevisionPicker, showChanges, showVersion,
} from './js/controls.js';
import { readRevisions } from './js/revisions.js';
import { readModel } from './js/legend.js';
import { finest, readModels } from './js/models.js';
import {
  flyTo, initCamera, placeCamera, setFinestResolution, updateControls,
} from './js/camera.js';
import { enableMerge } from './js/jobs.js';
import { followEvents } from './js/events.js';

export { DEPTH_PALETTE } from './js/palette.js';
export { depthOf } from './js/tileset.js';

function showStatus(text) {
  $('status').textContent = text;
}

initControls();
if (!modelId) {
  showStatus('no model: open /viewer/?model=ID');
  throw new Error('no model given (?model=ID)');
}
$('title').textContent = `VSM: ${modelId}`;
document.title = `VSM viewer: ${modelId}`;

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
initCamera(camera, controls, canvas);

setSun(state.sun.azimuth, state.sun.altitude);
startTiles(scene, camera, renderer);
enableMerge();

// ---- the model: legend, revisions, fly-to, live events ----------------------------------------

/// The legend, and the finest resolution for a free camera's near plane.
function readShownModel() {
  return readModel().then((info) => {
    setFinestResolution(info.resolution ? info.resolution.finest : null);
    return info;
  });
}

$('changes-legend').hidden = state.mode !== 'changes';
Promise.all([readShownModel(), readRevisions()]).then(() => {
  if (state.mode === 'changes' && !haveChanges()) {
    return showChanges();
  }
  return null;
}).catch((error) => console.warn(error));
initRevisionPicker();
let placed = false;
let flyPending = params.get('fly');
readModels(flyTo).then(() => {
  if (flyPending && placed) {
    flyTo(flyPending);
    flyPending = null;
  }
}).catch((error) => console.warn(error));
// A publish of the shown model replaces the tileset by the new version's and rereads the legend
// and fly-to areas (unless a kept revision is picked: then only the picker changes).
followEvents((data) => {
  readModels(flyTo).catch((error) => console.warn(error));
  if (data.model === modelId) {
    readRevisions().catch((error) => console.warn(error));
    if (state.revision === null) {
      showVersion(data.version);
      readShownModel().catch((error) => console.warn(error));
    }
  }
});

// ---- frames -----------------------------------------------------------------------------------

function onResize() {
  camera.aspect = window.innerWidth / window.innerHeight;
  camera.updateProjectionMatrix();
  renderer.setSize(window.innerWidth, window.innerHeight, false);
  currentTiles().setResolutionFromRenderer(camera, renderer);
  invalidate();
}
window.addEventListener('resize', onResize);

function rect(element) {
  const r = element.getBoundingClientRect();
  return { x: r.x, y: r.y, width: r.width, height: r.height };
}

function frame() {
  requestAnimationFrame(frame);
  const tiles = currentTiles();
  if (!placed) {
    placed = placeCamera(tiles);
    if (placed) {
      setEarthCentred(state.frame === 'earth');
      adaptToFrame(state.frame);
    }
    if (placed && flyPending && finest.has(flyPending)) {
      flyTo(flyPending);
      flyPending = null;
    }
  }
  updateControls();
  camera.updateMatrixWorld();
  tiles.update();
  if (drawIfChanged(renderer, scene, camera)) {
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
    (shown) => (state.mode === 'changes' ? { ...shown, change: changeOf(shown.key) } : shown));
  const stats = tiles.stats;
  state.rootLoaded = placed;
  state.pending = stats.queued + stats.downloading + stats.parsing;
  state.idle = placed && state.pending === 0 && !tiles.isLoading && flyPending === null;
  state.overlays = [rect($('panel')), rect($('legend'))];
  showStatus(`${MODE_NAMES[state.mode]}${state.lit || state.mode === 'relief' ? ', sun' : ''}: ` +
    `${state.loaded} tiles` +
    (state.pending ? `, ${state.pending} loading` : '') +
    (state.failed ? `, ${state.failed} FAILED` : ''));
}
frame();
