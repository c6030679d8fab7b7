// The other open models (GET /v1/models): the finest area of each (its deepest level's bounds) as
// a fly-to button, and each but the shown one as a source the merge button can merge in.

import { $, modelId, params } from './settings.js';
import { formatMetres, getJson } from './format.js';

/// Model id -> the bounds ({min, max}, global coordinates) of its deepest level.
export const finest = new Map();

/// Reads the models and fills the fly-to buttons (each calls `flyTo(id)`) and the merge sources.
export async function readModels(flyTo) {
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
