// The changes mode's data: each patch's displacement between two revisions (GET
// /v1/models/{m}/diff), as the signed value a tile is coloured by, and its legend (bottom right).

import { $, modelId, params, state } from './settings.js';
import { formatMetres, getJson } from './format.js';
import { changeColour } from './palette.js';
import { latestRevision } from './revisions.js';

/// {from, to, range, values: key -> signed metres}, or null while none is read.
let changes = null;

/// The displacement tile `key` is coloured by: the patch's largest signed one (0 when unchanged).
export function changeOf(key) {
  return changes ? changes.values.get(key) || 0 : 0;
}

/// The largest displacement of the whole diff (0 while none is read).
export function changeRange() {
  return changes ? changes.range : 0;
}

export function haveChanges() {
  return changes !== null;
}

export function forgetChanges() {
  changes = null;
  state.changes = null;
}

/// Reads the diff the changes mode shows: from ?from= or the kept revision before the shown one,
/// to the shown one, and writes its legend. The caller recolours the tiles.
export async function readChanges(latest = latestRevision()) {
  const to = state.revision !== null ? state.revision : latest;
  const earlier = state.revisions.map((r) => r.revision).filter((n) => n < to);
  const from = Number(params.get('from')) || earlier[earlier.length - 1];
  if (!from || !to) {
    state.changes = { error: 'no earlier revision to compare with' };
    return false;
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
  return true;
}
