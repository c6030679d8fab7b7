// Jobs on the panel: the merge button (POST /v1/jobs) and the progress of the last three jobs, as
// GET /v1/events reports them.

import { $, modelId, state } from './settings.js';

export function showJobs() {
  const lines = Object.entries(state.jobs).slice(-3).map(([id, job]) => {
    const what = `${job.type} ${job.models.join(' / ')}`;
    const how = job.state === 'running'
      ? `${Math.round(100 * job.progress)} %${job.stage ? ` (${job.stage})` : ''}`
      : job.state + (job.error ? `: ${job.error}` : '');
    return `${id}: ${what}: ${how}`;
  });
  $('jobs').textContent = lines.join('\n');
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

/// The merge button submits a merge job.
export function enableMerge() {
  $('merge').addEventListener('click', () => {
    submitMerge().catch((error) => {
      $('jobs').textContent = `merge failed: ${error.message}`;
    });
  });
}
