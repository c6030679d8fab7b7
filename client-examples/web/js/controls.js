// The panel's controls: mode, sun, height (vertical exaggeration) and revision. Each changes
// window.vsmViewer, redraws what it affects and keeps the URL in step.

import { $, MODES, setParam, state } from './settings.js';
import { currentTiles, recolour as recolourTiles, reloadTileset, reshape } from './tileset.js';
import { forgetChanges, readChanges } from './changes.js';
import { latestRevision } from './revisions.js';
import { readModel } from './legend.js';

/// Every tile in the material of the mode (and sun).
export function recolour() {
  if (currentTiles()) {
    recolourTiles();
  }
  setParam('lit', state.lit ? '1' : '0', '0');
}

/// Reads the diff of the changes mode (`latest`: the version the latest revision stands for),
/// then recolours; an error is kept in window.vsmViewer.changes.
export function showChanges(latest) {
  return readChanges(latest).then((read) => {
    if (read) {
      recolour();
    }
  });
}

function setMode(next) {
  state.mode = MODES.includes(next) ? next : 'lod';
  $('changes-legend').hidden = state.mode !== 'changes';
  if (state.mode === 'changes') {
    showChanges().catch((error) => {
      state.changes = { error: String(error) };
    });
  }
  recolour();
  setParam('mode', state.mode, 'lod');
}

function setExaggeration(k) {
  state.exaggeration = Math.max(k, 0);
  $('exaggeration-value').textContent = `${state.exaggeration}x`;
  reshape();
  setParam('exaggeration', String(state.exaggeration), '1');
}

/// Shows model version `version` (or the picked revision): the tileset and, in changes mode, its
/// diff.
export function showVersion(version) {
  reloadTileset(version);
  if (state.mode === 'changes') {
    forgetChanges();
    showChanges(version).catch((error) => {
      state.changes = { error: String(error) };
    });
  }
}

function pickRevision(value) {
  state.revision = value ? Number(value) : null;
  setParam('rev', state.revision === null ? '' : String(state.revision), '');
  showVersion(latestRevision());
  readModel().catch((error) => console.warn(error));
}

/// The mode, sun and height controls as the URL set them, and their listeners.
export function initControls() {
  for (const input of document.querySelectorAll('input[name=mode]')) {
    input.checked = input.value === state.mode;
    input.addEventListener('change', () => setMode(input.value));
  }
  $('lit').checked = state.lit;
  $('lit').addEventListener('change', () => {
    state.lit = $('lit').checked;
    recolour();
  });
  $('exaggeration').value = String(state.exaggeration);
  $('exaggeration-value').textContent = `${state.exaggeration}x`;
  $('exaggeration').addEventListener('input',
    () => setExaggeration(Number($('exaggeration').value)));
}

/// The revision picker's listener (its options come from readRevisions).
export function initRevisionPicker() {
  $('revision').addEventListener('change', (event) => pickRevision(event.target.value));
}

/// The controls for the model's frame: in a local one (no ellipsoid) there is no height above the
/// ellipsoid to exaggerate (an exaggeration=K of the URL is undone).
export function adaptToFrame(frame) {
  if (frame === 'local') {
    $('exaggeration').disabled = true;
    $('exaggeration').title = 'a model in a local frame has no height above the ellipsoid';
    if (state.exaggeration !== 1) {
      $('exaggeration').value = '1';
      setExaggeration(1);
    }
  }
}
