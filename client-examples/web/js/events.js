// Live: the page follows GET /v1/events. Job progress goes to the panel; a `published` event is
// recorded in window.vsmViewer.published and handed to `onPublished({model, version})`.

import { state } from './settings.js';
import { showJobs } from './jobs.js';

export function followEvents(onPublished) {
  const events = new EventSource('/v1/events');
  const onJob = (message) => {
    const data = JSON.parse(message.data);
    state.jobs[data.job] = {
      type: data.type,
      models: data.models,
      state: data.state,
      stage: data.stage,
      progress: data.progress === undefined ? 1 : data.progress,
      error: data.error ? data.error.message : null,
    };
    showJobs();
  };
  events.addEventListener('job', onJob);
  events.addEventListener('job_end', onJob);
  events.addEventListener('published', (message) => {
    const data = JSON.parse(message.data);
    state.published.push({ model: data.model, version: data.version,
      changed: data.changed_count });
    onPublished(data);
  });
}
