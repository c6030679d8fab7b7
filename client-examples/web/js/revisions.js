// The revision picker: the latest (followed as it is published) and each kept revision, with when
// and by which job it was made (GET /v1/models/{m}/revisions).

import { $, modelId, state } from './settings.js';
import { getJson } from './format.js';

export async function readRevisions() {
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
  select.value = state.revision === null ? '' : String(state.revision);
}

/// The newest revision listed (the model's version), else the version drawn.
export function latestRevision() {
  const latest = state.revisions.find((r) => r.latest);
  return latest ? latest.revision : state.version;
}
