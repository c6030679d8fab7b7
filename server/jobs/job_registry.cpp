#include "server/jobs/job_registry.hpp"

#include <algorithm>
#include <cstdio>
#include <ctime>

#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include "core/common/log.hpp"
#include "core/common/random.hpp"
#include "server/exec/pool_executor.hpp"
#include "server/exec/work_pool.hpp"

namespace vsm::server::jobs {

namespace {

/// The nice value of job threads.
constexpr int kJobNiceness = 10;

/// Jobs run at a lower CPU priority than request handlers (nice 10, i.e. about a tenth of the
/// share of a normal thread when both want a core): a merge uses what serving leaves, rather than
/// halving the request rate on a small machine. Per thread on Linux; once per job thread.
void lowerThreadPriority() {
  thread_local bool lowered = false;
  if (!lowered) {
    lowered = true;
    const auto tid = static_cast<id_t>(::syscall(SYS_gettid));
    if (::setpriority(PRIO_PROCESS, tid, kJobNiceness) != 0) {
      core::log::debug("job threads: cannot lower the priority (setpriority failed)");
    }
  }
}

}  // namespace

using core::Error;
using core::ErrorCode;
using nlohmann::json;
namespace log = core::log;

std::string_view toString(JobState state) {
  switch (state) {
    case JobState::Queued:
      return "queued";
    case JobState::Running:
      return "running";
    case JobState::Succeeded:
      return "succeeded";
    case JobState::Failed:
      return "failed";
    case JobState::Cancelled:
      return "cancelled";
  }
  return "failed";
}

bool isFinal(JobState state) {
  return state == JobState::Succeeded || state == JobState::Failed || state == JobState::Cancelled;
}

// ---- JobContext ------------------------------------------------------------------------------

void JobContext::plan(Plan plan) {
  double total = 0;
  for (const auto& [stage, share] : plan) {
    total += std::max(share, 0.0);
  }
  for (auto& [stage, share] : plan) {
    share = total > 0 ? std::max(share, 0.0) / total : 0;
  }
  const std::lock_guard lock(mutex_);
  plan_ = std::move(plan);
}

void JobContext::report(std::string_view stage, double fraction) {
  double overall = -1;  // stays so for a stage outside the plan
  {
    const std::lock_guard lock(mutex_);
    double before = 0;
    for (const auto& [name, share] : plan_) {
      if (name == stage) {
        overall = before + share * std::clamp(fraction, 0.0, 1.0);
        break;
      }
      before += share;
    }
  }
  update_(stage, overall);
}

// ---- JobRegistry -----------------------------------------------------------------------------

struct JobRegistry::Job {
  JobStatus status;
  JobWork work;
  std::unique_ptr<JobContext> context;
  std::string lane;  // empty: none
};

JobRegistry::JobRegistry(exec::WorkPool& pool, exec::WorkPool& helpers, JobLimits limits)
    : pool_(pool),
      executor_(
          std::make_unique<exec::PoolExecutor>(helpers, helpers.threads(), lowerThreadPriority)),
      limits_(limits),
      idPrefix_(core::randomWord()) {}

JobRegistry::~JobRegistry() = default;

JobStatus JobRegistry::submit(std::string type, json params, JobContext::Plan plan, JobWork work,
                              std::string lane) {
  auto job = std::make_shared<Job>();
  job->work = std::move(work);
  job->lane = std::move(lane);
  Job* raw = job.get();
  job->context.reset(new JobContext([this, raw](std::string_view stage, double overall) {
    std::optional<JobStatus> changed;
    {
      const std::lock_guard lock(mutex_);
      if (raw->status.state != JobState::Running) {
        return;
      }
      raw->status.stage = stage;
      if (overall >= 0) {
        raw->status.progress = std::max(raw->status.progress, std::min(overall, 1.0));
      }
      if (listener_) {
        changed = raw->status;
      }
    }
    if (changed) {
      tell(*changed);
    }
  }));
  job->context->plan(std::move(plan));
  job->status.type = std::move(type);
  job->status.params = std::move(params);
  job->status.created = std::chrono::system_clock::now();
  JobStatus out;
  bool post = true;
  {
    const std::lock_guard lock(mutex_);
    if (closed_) {
      throw Error(ErrorCode::Unavailable, "the daemon is stopping; no new jobs");
    }
    const auto active = std::count_if(jobs_.begin(), jobs_.end(), [](const auto& entry) {
      return !isFinal(entry.second->status.state);
    });
    if (static_cast<std::size_t>(active) >= limits_.active) {
      throw Error(ErrorCode::Unavailable, "too many jobs queued or running (" +
                                              std::to_string(limits_.active) + "); retry later");
    }
    char id[24];
    std::snprintf(id, sizeof id, "%08x%08llx", idPrefix_, static_cast<unsigned long long>(++next_));
    job->status.id = limits_.node.empty() ? std::string(id) : limits_.node + "-" + id;
    job->context->id_ = job->status.id;
    job->context->executor_ = executor_.get();
    jobs_.emplace(job->status.id, job);
    order_.push_back(job->status.id);
    out = job->status;
    if (!job->lane.empty()) {
      auto& waiting = lanes_[job->lane];
      waiting.push_back(job);
      post = waiting.size() == 1;
    }
  }
  log::info("job=" + out.id + " queued: " + out.type + " " + out.params.dump());
  tell(out);
  if (post) {
    pool_.post([this, job] { run(job); });
  }
  return out;
}

void JobRegistry::advance(const std::string& lane) {
  std::shared_ptr<Job> next;
  {
    const std::lock_guard lock(mutex_);
    const auto it = lanes_.find(lane);
    if (it == lanes_.end()) {
      return;
    }
    it->second.pop_front();
    if (it->second.empty()) {
      lanes_.erase(it);
      return;
    }
    next = it->second.front();
  }
  pool_.post([this, next] { run(next); });
}

void JobRegistry::run(const std::shared_ptr<Job>& job) {
  JobWork work;
  JobStatus running;
  bool cancelledWhileQueued = false;
  {
    const std::lock_guard lock(mutex_);
    if (job->status.state != JobState::Queued) {
      cancelledWhileQueued = true;
    } else {
      job->status.state = JobState::Running;
      job->status.stage = "starting";
      job->status.started = std::chrono::system_clock::now();
      work = std::move(job->work);
      running = job->status;
    }
  }
  if (cancelledWhileQueued) {
    if (!job->lane.empty()) {
      advance(job->lane);
    }
    return;
  }
  log::info("job=" + running.id + " running");
  tell(running);
  lowerThreadPriority();
  json result;
  JobState state = JobState::Succeeded;
  std::optional<ErrorCode> code;
  std::string message;
  try {
    result = work(*job->context);
  } catch (const Error& e) {
    code = e.code();
    message = e.what();
    state = e.code() == ErrorCode::Cancelled ? JobState::Cancelled : JobState::Failed;
  } catch (const std::exception& e) {
    code = ErrorCode::Internal;
    message = e.what();
    state = JobState::Failed;
  } catch (...) {
    code = ErrorCode::Internal;
    message = "a non-exception was thrown";
    state = JobState::Failed;
  }
  // Whatever the work held (models, leases, an unpublished edit) goes before the job is shown
  // final: a client seeing "succeeded" or "cancelled" may close the model at once.
  work = nullptr;
  finish(*job, state, std::move(result), code, std::move(message));
  if (!job->lane.empty()) {
    advance(job->lane);
  }
}

void JobRegistry::finish(Job& job, JobState state, json result, std::optional<ErrorCode> code,
                         std::string message) {
  std::string line;
  JobStatus final;
  {
    const std::lock_guard lock(mutex_);
    JobStatus& s = job.status;
    s.state = state;
    s.finished = std::chrono::system_clock::now();
    if (state == JobState::Succeeded) {
      s.progress = 1;
      s.stage = "done";
      s.result = std::move(result);
    } else {
      s.errorCode = code;
      s.errorMessage = std::move(message);
    }
    line = "job=" + s.id + " " + std::string(toString(state));
    if (state != JobState::Succeeded) {
      line += " in stage " + s.stage + ": " + s.errorMessage;
    }
    final = s;
    forgetOldFinished();
  }
  if (state == JobState::Failed) {
    log::warn(line);
  } else {
    log::info(line);
  }
  tell(final);
}

void JobRegistry::forgetOldFinished() {
  std::size_t finished = 0;
  for (const auto& [id, job] : jobs_) {
    finished += isFinal(job->status.state) ? 1 : 0;
  }
  for (auto it = order_.begin(); it != order_.end() && finished > limits_.finished;) {
    const auto job = jobs_.find(*it);
    if (job != jobs_.end() && isFinal(job->second->status.state)) {
      jobs_.erase(job);
      it = order_.erase(it);
      --finished;
    } else {
      ++it;
    }
  }
}

std::vector<JobStatus> JobRegistry::list() const {
  std::vector<JobStatus> out;
  const std::lock_guard lock(mutex_);
  out.reserve(order_.size());
  for (const std::string& id : order_) {
    out.push_back(jobs_.at(id)->status);
  }
  return out;
}

JobStatus JobRegistry::get(std::string_view id) const {
  const std::lock_guard lock(mutex_);
  const auto it = jobs_.find(id);
  if (it == jobs_.end()) {
    throw Error(ErrorCode::NotFound, "no job '" + std::string(id.substr(0, 64)) + "'");
  }
  return it->second->status;
}

JobStatus JobRegistry::cancel(std::string_view id) {
  JobWork dropped;  // a queued job's work, destroyed outside the lock
  JobStatus out;
  bool cancelledNow = false;
  {
    const std::lock_guard lock(mutex_);
    const auto it = jobs_.find(id);
    if (it == jobs_.end()) {
      throw Error(ErrorCode::NotFound, "no job '" + std::string(id.substr(0, 64)) + "'");
    }
    Job& job = *it->second;
    if (isFinal(job.status.state)) {
      throw Error(ErrorCode::Conflict, "job '" + job.status.id + "' has " +
                                           std::string(toString(job.status.state)) + " already");
    }
    job.status.cancelRequested = true;
    job.context->cancel_.cancel();
    if (job.status.state == JobState::Queued) {
      dropped = std::move(job.work);
      job.status.state = JobState::Cancelled;
      job.status.finished = std::chrono::system_clock::now();
      job.status.errorCode = ErrorCode::Cancelled;
      job.status.errorMessage = "cancelled before it started";
      cancelledNow = true;
    }
    out = job.status;
  }
  log::info("job=" + out.id + (cancelledNow ? " cancelled while queued" : " cancel requested"));
  if (cancelledNow) {
    tell(out);  // final; a running job tells its own end (its next report shows the request)
  }
  return out;
}

void JobRegistry::cancelAll(bool refuseNew) {
  std::vector<std::string> ids;
  {
    const std::lock_guard lock(mutex_);
    closed_ = closed_ || refuseNew;
    for (const auto& [id, job] : jobs_) {
      if (!isFinal(job->status.state)) {
        ids.push_back(id);
      }
    }
  }
  for (const std::string& id : ids) {
    try {
      cancel(id);
    } catch (const Error&) {
      // finished meanwhile
    }
  }
}

void JobRegistry::onChange(std::function<void(const JobStatus&)> listener) {
  listener_ = std::move(listener);
}

void JobRegistry::tell(const JobStatus& status) const {
  if (listener_) {
    listener_(status);
  }
}

std::map<JobState, std::size_t> JobRegistry::counts() const {
  std::map<JobState, std::size_t> out;
  for (const JobState state : kJobStates) {
    out[state] = 0;
  }
  const std::lock_guard lock(mutex_);
  for (const auto& [id, job] : jobs_) {
    ++out[job->status.state];
  }
  return out;
}

namespace {

json timeJson(const std::optional<std::chrono::system_clock::time_point>& time) {
  if (!time) {
    return nullptr;
  }
  const auto since = time->time_since_epoch();
  const std::time_t seconds = std::chrono::duration_cast<std::chrono::seconds>(since).count();
  const auto millis = std::chrono::duration_cast<std::chrono::milliseconds>(since).count() % 1000;
  std::tm utc{};
  gmtime_r(&seconds, &utc);
  char text[64];
  std::snprintf(text, sizeof text, "%04d-%02d-%02dT%02d:%02d:%02d.%03dZ", utc.tm_year + 1900,
                utc.tm_mon + 1, utc.tm_mday, utc.tm_hour, utc.tm_min, utc.tm_sec,
                static_cast<int>(millis));
  return text;
}

}  // namespace

json toJson(const JobStatus& s) {
  json error = nullptr;
  if (s.errorCode) {
    error = {{"code", core::toString(*s.errorCode)}, {"message", s.errorMessage}};
  }
  return {
      {"id", s.id},
      {"type", s.type},
      {"params", s.params},
      {"state", toString(s.state)},
      {"stage", s.stage},
      {"progress", s.progress},
      {"cancel_requested", s.cancelRequested},
      {"error", std::move(error)},
      {"result", s.result.is_null() ? json(nullptr) : s.result},
      {"created_at", timeJson(s.created)},
      {"started_at", timeJson(s.started)},
      {"finished_at", timeJson(s.finished)},
  };
}

}  // namespace vsm::server::jobs
