// The model's 3D Tiles (GET /v1/models/{m}/3dtiles/tileset.json) streamed by 3d-tiles-renderer:
// one renderer per version shown, its counters, the tiles it draws, and the meshes' shapes and
// materials kept in step with the controls.

import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { MeshoptDecoder } from 'three/addons/libs/meshopt_decoder.module.js';
import { TilesRenderer } from '3d-tiles-renderer';
import { modelId, newCounts, params, state } from './settings.js';
import { invalidate } from './frames.js';
import { materialFor, releaseMaterials } from './materials.js';
import { shapeMesh } from './exaggeration.js';

const errorTarget = Number(params.get('error'));
const tilesetBase = params.get('tileset') ||
  new URL(`/v1/models/${encodeURIComponent(modelId)}/3dtiles/tileset.json`,
    window.location.href).toString();

/// The depth of a tile from its content URL (".../3dtiles/2_1_3.glb" -> 2); null if it has none.
export function depthOf(url) {
  const match = /(?:^|\/)(\d+)_\d+_\d+\.glb(?:[?#].*)?$/.exec(url || '');
  return match ? Number(match[1]) : null;
}

/// The patch key of a tile from its content URL (".../2_1_3.glb?v=4" -> "2_1_3"); null if none.
export function keyOf(url) {
  const match = /(?:^|\/)(\d+_\d+_\d+)\.glb(?:[?#].*)?$/.exec(url || '');
  return match ? match[1] : null;
}

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
function makeTiles(url, camera, renderer) {
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
        releaseMaterials(object);
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
  if (state.revision !== null) {
    url.searchParams.set('rev', String(state.revision));
  } else if (version !== null) {
    url.searchParams.set('v', String(version));
  }
  return url.toString();
}

let scene = null;
let camera = null;
let renderer = null;
let tiles = null;

/// Starts streaming the latest version into `scene`, seen by `camera` through `renderer`.
export function startTiles(sceneArg, cameraArg, rendererArg) {
  scene = sceneArg;
  camera = cameraArg;
  renderer = rendererArg;
  tiles = makeTiles(tilesetUrl(null), camera, renderer);
  scene.add(tiles.group);
}

/// The renderer of the version shown.
export function currentTiles() {
  return tiles;
}

/// Replaces the tileset by model version `version`'s (the URL names it, so no cache answers the
/// old one), or by the picked revision's. Unchanged tiles keep their URIs, so the browser's cache
/// answers them; the changed ones load anew. (Loading the new version beside the old one and
/// swapping when it is complete would avoid the moment of coarser tiles, but 3d-tiles-renderer's
/// renderers share one tile cache and queues, and the second one starved.)
export function reloadTileset(version) {
  scene.remove(tiles.group);
  tiles.dispose();
  tiles = makeTiles(tilesetUrl(version), camera, renderer);
  scene.add(tiles.group);
  invalidate();
  state.version = state.revision !== null ? state.revision : version;
  state.reloads++;
  state.idle = false;
}

function forEachTileMesh(visit) {
  tiles.group.traverse((object) => {
    if (object.isMesh && object.userData.vsmOwnMaterial) {
      visit(object);
    }
  });
}

/// Every drawn mesh in the material of the current mode (and lit).
export function recolour() {
  forEachTileMesh((object) => {
    object.material = materialFor(object);
  });
  invalidate();
}

/// Every drawn mesh in the shape of the current exaggeration.
export function reshape() {
  forEachTileMesh(shapeMesh);
  invalidate();
}
