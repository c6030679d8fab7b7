#include "server/api/job_routes.hpp"

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "server/api/requests.hpp"
#include "server/cluster/coordinator.hpp"
#include "server/jobs/job_registry.hpp"
#include "server/jobs/model_jobs.hpp"

namespace vsm::server::api {

using core::Error;
using core::ErrorCode;
using nlohmann::json;

namespace {

http::Response jobResponse(int status, const jobs::JobStatus& job) {
  http::Response response = http::jsonResponse(status, jobs::toJson(job));
  response.set("Cache-Control", std::string(http::cache_control::kNoStore));
  return response;
}

http::Response postJob(const ModelContext& c, const http::Request& request) {
  const MergeRequest body = parseMergeRequest(request);
  if (auto redirect = redirectToWriter(c, body.target, request)) {
    return std::move(*redirect);
  }
  const jobs::JobStatus job =
      jobs::submitMerge(c.jobs, c.models, body.target, body.source, body.registerFirst);
  http::Response response = jobResponse(202, job);
  response.set("Location", "/v1/jobs/" + job.id);
  return response;
}

/// In a cluster, a job of another node ("<node>-<hex>", see JobLimits::node): 307 to the same
/// target on that node. nullopt for a job of this node, or with no cluster.
std::optional<http::Response> redirectToJobNode(const ModelContext& c,
                                                const http::Request& request) {
  if (c.cluster == nullptr) {
    return std::nullopt;
  }
  const std::string& id = request.param("j");
  const std::size_t dash = id.rfind('-');
  if (dash == std::string::npos || id.substr(0, dash) == c.cluster->node()) {
    return std::nullopt;
  }
  const std::string node = id.substr(0, dash);
  const std::optional<std::string> url = c.cluster->nodeUrl(node);
  if (!url) {
    throw Error(ErrorCode::NotFound, "no job '" + id.substr(0, 64) + "': node '" +
                                         node.substr(0, 32) + "' is not in the cluster (any more)");
  }
  return temporaryRedirect(*url + request.target, "job of node " + node);
}

}  // namespace

void addJobRoutes(http::Router& router, ModelContext context) {
  router.add(http::Method::Get, "/v1/jobs", [context](const http::Request&) {
    json list = json::array();
    for (const jobs::JobStatus& job : context.jobs.list()) {
      list.push_back(jobs::toJson(job));
    }
    http::Response response = http::jsonResponse(200, {{"jobs", std::move(list)}});
    response.set("Cache-Control", std::string(http::cache_control::kNoStore));
    return response;
  });
  router.add(http::Method::Post, "/v1/jobs",
             [context](const http::Request& request) { return postJob(context, request); });
  router.add(http::Method::Get, "/v1/jobs/{j}", [context](const http::Request& request) {
    if (auto redirect = redirectToJobNode(context, request)) {
      return std::move(*redirect);
    }
    return jobResponse(200, context.jobs.get(request.param("j")));
  });
  router.add(http::Method::Delete, "/v1/jobs/{j}", [context](const http::Request& request) {
    if (auto redirect = redirectToJobNode(context, request)) {
      return std::move(*redirect);
    }
    const jobs::JobStatus job = context.jobs.cancel(request.param("j"));
    // Cancelled at once when it was queued (200); otherwise it stops at its next check (202).
    return jobResponse(jobs::isFinal(job.state) ? 200 : 202, job);
  });
}

}  // namespace vsm::server::api
