// The page's settings, read from its URL, and window.vsmViewer: the state every part of the viewer
// keeps up to date and tests and scripts read (its fields are listed in main.js).

export const MODES = ['lod', 'relief', 'texture', 'changes'];
export const MODE_NAMES = {
  lod: 'level of detail', relief: 'relief', texture: 'texture', changes: 'changes',
};
const DEFAULT_SUN = [315, 45];

export const params = new URLSearchParams(window.location.search);
export const modelId = params.get('model');

const sunParam = (params.get('sun') || '').split(',').map(Number);
const sun = sunParam.length === 2 && sunParam.every(Number.isFinite) ? sunParam : DEFAULT_SUN;
const rev = Number(params.get('rev'));

/// The counters of one tileset's renderer (the drawn one's are copied into window.vsmViewer).
export function newCounts() {
  return { requested: 0, loaded: 0, textured: 0, failed: 0, errors: [], depths: {} };
}

/// The one copy of what the page shows: mode, lit, exaggeration and revision (null: the latest,
/// following publishes) are read here by every module and changed only by the controls.
export const state = {
  model: modelId,
  mode: MODES.includes(params.get('mode')) ? params.get('mode') : 'lod',
  lit: params.get('lit') === '1',
  view: params.get('view') === 'top' ? 'top' : 'oblique',
  sun: { azimuth: sun[0], altitude: sun[1] },
  exaggeration: Math.max(Number(params.get('exaggeration')) || 1, 0),
  ...newCounts(),
  rootLoaded: false,
  pending: 0,
  idle: false,
  frames: 0,
  version: null,
  revision: Number.isInteger(rev) && rev > 0 ? rev : null,
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
  frame: null,
  near: null,
};
window.vsmViewer = state;

export const $ = (id) => document.getElementById(id);

/// Keeps the URL in step with the controls, so that a reload or a shared link shows the same.
export function setParam(name, value, fallback) {
  const url = new URL(window.location.href);
  if (value === fallback) {
    url.searchParams.delete(name);
  } else {
    url.searchParams.set(name, value);
  }
  window.history.replaceState(null, '', url);
}
