// GET /v1/events and what feeds it: jobs and models to wire events (see proto/openapi.yaml).
#include "server/api/event_routes.hpp"

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "server/events/event_hub.hpp"
#include "server/jobs/job_registry.hpp"
#include "server/models/model_registry.hpp"

namespace vsm::server::api {

using nlohmann::json;

namespace {

/// The models a job works on, from its parameters: an import's id, a merge's target and source,
/// a restore's model.
json jobModels(const jobs::JobStatus& status) {
  json models = json::array();
  for (const char* name : {"id", "target", "source", "model"}) {
    if (const auto it = status.params.find(name); it != status.params.end() && it->is_string()) {
      models.push_back(*it);
    }
  }
  return models;
}

}  // namespace

json jobEventJson(const jobs::JobStatus& s) {
  return {{"job", s.id},
          {"type", s.type},
          {"models", jobModels(s)},
          {"state", jobs::toString(s.state)},
          {"stage", s.stage},
          {"progress", s.progress},
          {"cancel_requested", s.cancelRequested}};
}

json jobEndJson(const jobs::JobStatus& s) {
  json error = nullptr;
  if (s.errorCode) {
    error = {{"code", core::toString(*s.errorCode)}, {"message", s.errorMessage}};
  }
  return {{"job", s.id},
          {"type", s.type},
          {"models", jobModels(s)},
          {"state", jobs::toString(s.state)},
          {"stage", s.stage},
          {"error", std::move(error)},
          {"result", s.result.is_null() ? json(nullptr) : s.result}};
}

void addEventRoutes(http::Router& router, events::EventHub& hub) {
  // Subscribing takes a lock for a moment and allocates: fit for the network thread, so a full
  // CPU pool cannot keep a client from its stream.
  const auto subscribe = [&hub](const http::Request& request) {
    http::Response response;
    response.contentType = "text/event-stream";
    response.set("Cache-Control", "no-store");
    response.set("X-Accel-Buffering", "no");          // nginx: pass each event on at once
    response.stream = hub.subscribe(request.client);  // limits.event_subscribers_per_client
    return response;
  };
  router.add(http::Method::Get, "/v1/events", subscribe,
             [subscribe](const http::Request& request) -> std::optional<http::Response> {
               return subscribe(request);
             });
}

void connectEvents(events::EventHub& hub, jobs::JobRegistry& jobs, models::ModelRegistry& models) {
  jobs.onChange([&hub](const jobs::JobStatus& status) {
    if (jobs::isFinal(status.state)) {
      hub.settle(status.id);  // held-back progress is obsolete: the end says it all
      hub.publish("job_end", jobEndJson(status));
    } else if (status.state == jobs::JobState::Queued) {
      hub.publish("job", jobEventJson(status));  // once per job: not coalesced
    } else {
      hub.progress(status.id, "job", jobEventJson(status));
    }
  });
  models.onPublished([&hub](const models::ModelRegistry::Publication& publication) {
    json changed = json::array();
    json removed = json::array();
    const bool complete = publication.changed.size() + publication.removed.size() <= kMaxListedKeys;
    if (complete) {
      for (const core::PatchKey& key : publication.changed) {
        changed.push_back(key.toString());
      }
      for (const core::PatchKey& key : publication.removed) {
        removed.push_back(key.toString());
      }
    }
    hub.publish("published", {{"model", publication.model},
                              {"version", publication.version},
                              {"changed", std::move(changed)},
                              {"changed_count", publication.changed.size()},
                              {"removed", std::move(removed)},
                              {"removed_count", publication.removed.size()},
                              {"changed_complete", complete},
                              {"followed", publication.followed}});
  });
}

}  // namespace vsm::server::api
