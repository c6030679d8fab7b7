// The legend (bottom left): each depth of the model in its palette colour with its resolution
// (mean distance between grid neighbours), from GET /v1/models/{m} of the revision shown.

import { $, modelId, state } from './settings.js';
import { formatMetres, getJson } from './format.js';
import { paletteColour } from './palette.js';

/// Reads the model shown and fills the legend; the model's summary.
export async function readModel() {
  const info = await getJson(`/v1/models/${encodeURIComponent(modelId)}` +
    (state.revision !== null ? `?rev=${state.revision}` : ''));
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
