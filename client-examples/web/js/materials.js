// The material a tile's mesh shows in each mode: mode=lod its depth's palette colour, relief grey
// shaded by the sun, texture the GLB's image (an untextured tile as in relief), changes its
// displacement on the diverging scale. lod, texture and changes are unlit (exact palette colours,
// the image's own colours, as imagery is shown) unless lit.

import * as THREE from 'three';
import { state } from './settings.js';
import { CHANGE_BINS, RELIEF_GREY, changeColour, paletteColour, DEPTH_PALETTE } from './palette.js';
import { sunMaterial } from './shading.js';
import { changeOf, changeRange } from './changes.js';

const reliefMaterial = sunMaterial(RELIEF_GREY);

/// Materials per depth shared by its tiles: unlit (the exact palette colour) and lit.
const lodMaterials = new Map();
function lodMaterial(depth) {
  const key = `${Math.min(depth, DEPTH_PALETTE.length - 1)}${state.lit ? 'lit' : ''}`;
  if (!lodMaterials.has(key)) {
    lodMaterials.set(key, state.lit ? sunMaterial(paletteColour(depth))
      : new THREE.MeshBasicMaterial({
        color: new THREE.Color(paletteColour(depth)),
        side: THREE.DoubleSide,
      }));
  }
  return lodMaterials.get(key);
}

/// The material a textured mesh shows in texture mode, made once per mesh and disposed with it
/// (releaseMaterials): unlit (a MeshBasicMaterial with the image and colour of its own) or lit by
/// the sun.
function textureMaterial(object) {
  const own = object.userData.vsmOwnMaterial;
  const key = state.lit ? 'vsmLitMaterial' : 'vsmUnlitMaterial';
  if (!object.userData[key]) {
    object.userData[key] = state.lit ? sunMaterial('#ffffff', own.map)
      : new THREE.MeshBasicMaterial({
        map: own.map,
        color: own.color,
        side: own.side,
        transparent: own.transparent,
        opacity: own.opacity,
      });
  }
  return object.userData[key];
}

/// Materials per step of the changes scale, shared by its tiles: unlit and lit.
const changeMaterials = new Map();
function changeMaterial(value) {
  const range = changeRange();
  const t = range > 0 ? Math.max(-1, Math.min(1, value / range)) : 0;
  const bin = Math.round(t * CHANGE_BINS);
  const key = `${bin}${state.lit ? 'lit' : ''}`;
  if (!changeMaterials.has(key)) {
    const colour = changeColour(bin / CHANGE_BINS);
    changeMaterials.set(key, state.lit ? sunMaterial(`#${colour.getHexString()}`)
      : new THREE.MeshBasicMaterial({ color: colour, side: THREE.DoubleSide }));
  }
  return changeMaterials.get(key);
}

/// The material of a tile's mesh (its userData: vsmOwnMaterial, vsmDepth, vsmKey) in the mode.
export function materialFor(object) {
  if (state.mode === 'changes') {
    return changeMaterial(changeOf(object.userData.vsmKey));
  }
  if (state.mode === 'lod' && object.userData.vsmDepth !== null) {
    return lodMaterial(object.userData.vsmDepth);
  }
  return state.mode === 'texture' && object.userData.vsmOwnMaterial.map
    ? textureMaterial(object) : reliefMaterial;
}

/// A tile's mesh going away: its own material back (the renderer disposes it, not ours) and ours
/// disposed (the image is the renderer's).
export function releaseMaterials(object) {
  object.material = object.userData.vsmOwnMaterial;
  for (const key of ['vsmUnlitMaterial', 'vsmLitMaterial']) {
    if (object.userData[key]) {
      object.userData[key].dispose();
      delete object.userData[key];
    }
  }
}
