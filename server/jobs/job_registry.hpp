#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/common/executor.hpp"
#include "core/common/progress.hpp"

namespace vsm::server::exec {
class PoolExecutor;
class WorkPool;
}  // namespace vsm::server::exec

namespace vsm::server::jobs {

enum class JobState { Queued, Running, Succeeded, Failed, Cancelled };
inline constexpr JobState kJobStates[] = {JobState::Queued, JobState::Running, JobState::Succeeded,
                                          JobState::Failed, JobState::Cancelled};
/// "queued", "running", "succeeded", "failed", "cancelled".
std::string_view toString(JobState state);
bool isFinal(JobState state);

/// What a client sees of a job: a copy, taken under the registry's lock.
struct JobStatus {
  std::string id;
  /// "merge", "import".
  std::string type;
  /// The request's parameters as the job understood them (JSON object).
  nlohmann::json params = nlohmann::json::object();
  JobState state = JobState::Queued;
  /// The step running now ("queued", "matching", "placing", ...; the last one when final).
  std::string stage = "queued";
  /// 0..1, never decreasing; 1 once succeeded.
  double progress = 0;
  /// A DELETE asked for cancellation (the job stops at its next check).
  bool cancelRequested = false;
  /// Set when failed or cancelled.
  std::optional<core::ErrorCode> errorCode;
  std::string errorMessage;
  /// What the job produced (JSON object), when succeeded.
  nlohmann::json result;
  std::chrono::system_clock::time_point created;
  std::optional<std::chrono::system_clock::time_point> started;
  std::optional<std::chrono::system_clock::time_point> finished;
};

/// The job's side of progress and cancellation: a core::Progress adapter that maps the stages an
/// operation reports onto one fraction 0..1 by a plan of weighted stages. Stages not in the plan
/// are shown but do not move the fraction. Thread-safe (the job reports, clients read).
class JobContext final : public core::Progress {
 public:
  /// One planned stage and its share of the whole (shares are normalised to sum 1).
  using Plan = std::vector<std::pair<std::string, double>>;

  /// Reports a stage and its own fraction 0..1.
  void report(std::string_view stage, double fraction) override;
  /// Polled by the operation; set by cancel().
  const core::CancelToken& cancelToken() const { return cancel_; }
  /// Throws core::Error(Cancelled) after cancel().
  void throwIfCancelled() const { cancel_.throwIfCancelled(); }
  /// Replaces the plan (before the operation starts reporting).
  void plan(Plan plan);
  /// The job's id (set before the work runs).
  const std::string& id() const { return id_; }
  /// Threads the operation may run its tasks on (core::MergeOptions::executor, ...): the job's
  /// own and the helper pool's threads that are free (exec::PoolExecutor).
  core::Executor& executor() const { return *executor_; }

 private:
  friend class JobRegistry;
  JobContext(std::function<void(std::string_view, double)> update) : update_(std::move(update)) {}

  std::function<void(std::string_view, double)> update_;
  std::string id_;
  core::Executor* executor_ = nullptr;
  core::CancelToken cancel_;
  mutable std::mutex mutex_;  // guards plan_
  Plan plan_;
};

/// The work of a job: runs on the job pool, reports through the context, polls its cancel token,
/// and returns its result (a JSON object) or throws (core::Error(Cancelled) when cancelled).
/// Whatever it holds (models, leases, edits) it releases when it returns or throws.
using JobWork = std::function<nlohmann::json(JobContext&)>;

struct JobLimits {
  /// Jobs queued or running at once; one more is refused with core::Error(Unavailable).
  std::size_t active = 16;
  /// Finished jobs remembered (oldest forgotten first).
  std::size_t finished = 100;
  /// In a cluster, the node's name: job ids are then "<node>-<hex>", so that any node can tell
  /// whose job an id names.
  std::string node;
};

/// Every job of this process: queued, running, and the last finished ones. Jobs run on a WorkPool
/// (the daemon's job pool); state lives in memory only, so a restart forgets them (an unfinished
/// merge never published, so its model reopens at its last published version).
///
/// Thread-safe. One mutex guards the table and every job's status; it is never held while work
/// runs or a callback is called.
class JobRegistry {
 public:
  /// Jobs run on `pool`; the tasks they hand JobContext::executor() run on their own thread and
  /// on `helpers`' free threads. `helpers` is a pool of its own: a job's tasks held up (a stalled
  /// disk) then hold no thread another job needs. Both must outlive the registry, and be joined
  /// before it is destroyed (`pool` first).
  JobRegistry(exec::WorkPool& pool, exec::WorkPool& helpers, JobLimits limits = {});
  ~JobRegistry();
  JobRegistry(const JobRegistry&) = delete;
  JobRegistry& operator=(const JobRegistry&) = delete;

  /// Queues `work`. Jobs given the same non-empty `lane` (the model they write) run one at a time,
  /// in submission order; other jobs run as the pool has threads. Returns its status (queued).
  /// Throws core::Error(Unavailable) when the active cap is reached or the registry is shutting
  /// down.
  JobStatus submit(std::string type, nlohmann::json params, JobContext::Plan plan, JobWork work,
                   std::string lane = {});

  /// Every remembered job, oldest first.
  std::vector<JobStatus> list() const;
  /// Throws core::Error(NotFound).
  JobStatus get(std::string_view id) const;
  /// Asks a job to stop: a queued one is cancelled at once, a running one at its next check.
  /// Returns its status afterwards. Throws core::Error(NotFound), Conflict when it has finished.
  JobStatus cancel(std::string_view id);
  /// Cancels everything queued or running; with `refuseNew`, refuses new jobs from now on
  /// (shutdown). Without it (a cluster node that lost its lease), new jobs are still taken.
  void cancelAll(bool refuseNew = true);
  /// Jobs per state, for metrics.
  std::map<JobState, std::size_t> counts() const;

  /// Sets the one function told of every change of a job (queued, running, each progress report,
  /// final), with its status then; on the thread that changed it (the submitting, the job's, the
  /// cancelling one), with no lock held, in the order the changes happened for one job. It must
  /// not throw or block. Call before the first submit().
  void onChange(std::function<void(const JobStatus&)> listener);

 private:
  struct Job;
  void run(const std::shared_ptr<Job>& job);
  /// After the job at the head of `lane` ended (or was found cancelled): posts the next one.
  void advance(const std::string& lane);
  void finish(Job& job, JobState state, nlohmann::json result, std::optional<core::ErrorCode> code,
              std::string message);
  void forgetOldFinished();

  void tell(const JobStatus& status) const;

  exec::WorkPool& pool_;
  /// Over the helper pool, lent to every job (JobContext::executor).
  std::unique_ptr<exec::PoolExecutor> executor_;
  JobLimits limits_;
  std::function<void(const JobStatus&)> listener_;  // set before the first job
  std::uint32_t idPrefix_;
  mutable std::mutex mutex_;  // guards everything below and every Job::status
  std::uint64_t next_ = 0;
  bool closed_ = false;
  std::map<std::string, std::shared_ptr<Job>, std::less<>> jobs_;
  std::deque<std::string> order_;  // ids, oldest first
  /// Lane -> its jobs not yet ended, in submission order; the first one is posted to the pool.
  std::map<std::string, std::deque<std::shared_ptr<Job>>, std::less<>> lanes_;
};

/// A job's status as JSON (proto/examples/job.json).
nlohmann::json toJson(const JobStatus& status);

}  // namespace vsm::server::jobs
