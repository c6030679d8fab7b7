#pragma once

#include <nlohmann/json_fwd.hpp>

#include "server/http/router.hpp"

namespace vsm::server::events {
class EventHub;
}
namespace vsm::server::jobs {
struct JobStatus;
class JobRegistry;
}  // namespace vsm::server::jobs
namespace vsm::server::models {
class ModelRegistry;
}

namespace vsm::server::api {

/// GET /v1/events: a Server-Sent Events stream of `hub` (see proto/openapi.yaml), counted under
/// the request's client address (limits.event_subscribers_per_client). `hub` must outlive the
/// router.
void addEventRoutes(http::Router& router, events::EventHub& hub);

/// Feeds `hub` with the jobs' changes (event "job", coalesced per job, and "job_end") and the
/// models' new versions (event "published"). Call before jobs are submitted and models opened;
/// `hub` must outlive both registries' jobs and models.
void connectEvents(events::EventHub& hub, jobs::JobRegistry& jobs, models::ModelRegistry& models);

/// The most keys a "published" event lists; beyond it the list is left out (changed_complete
/// false), so that one event stays far below a subscriber's queue bound.
inline constexpr std::size_t kMaxListedKeys = 4096;

// ---- wire mapping, public for tests -----------------------------------------------------------

/// The data of a "job" event: {"job", "type", "models", "state", "stage", "progress",
/// "cancel_requested"}.
nlohmann::json jobEventJson(const jobs::JobStatus& status);
/// The data of a "job_end" event: {"job", "type", "models", "state", "stage", "error", "result"}.
nlohmann::json jobEndJson(const jobs::JobStatus& status);

}  // namespace vsm::server::api
