// server/jobs: the job registry (stages, cancellation, failures, the queue's bound, cluster ids)
// and the executor it lends its jobs (server/exec/pool_executor).
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <set>
#include <stdexcept>
#include <string>
#include <thread>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "server/exec/pool_executor.hpp"
#include "server/exec/work_pool.hpp"
#include "server/jobs/job_registry.hpp"
#include "tests/unit/server_test_support.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::server {
namespace {

using core::Error;
using core::ErrorCode;
using core::test::codeOf;
using nlohmann::json;
using test::waitFinal;
using namespace std::chrono_literals;

// ---- jobs ------------------------------------------------------------------------------------

/// A gate a test opens to let a job go on.
class Gate {
 public:
  void open() {
    {
      const std::lock_guard lock(mutex_);
      open_ = true;
    }
    cv_.notify_all();
  }
  void wait() {
    std::unique_lock lock(mutex_);
    cv_.wait(lock, [this] { return open_; });
  }

 private:
  std::mutex mutex_;
  std::condition_variable cv_;
  bool open_ = false;
};

TEST(JobRegistry, RunsAJobAndMapsStagesOntoOneRisingFraction) {
  exec::WorkPool pool("jobs", 1);
  exec::WorkPool helpers("job-helpers", 1);
  jobs::JobRegistry registry(pool, helpers);
  Gate halfway;
  Gate resume;
  const auto job = registry.submit(
      "test", {{"a", 1}}, {{"first", 1}, {"second", 3}}, [&](jobs::JobContext& context) {
        context.report("first", 1);
        context.report("second", 0.5);
        context.report("unplanned", 0.1);  // shown, but the fraction stays
        halfway.open();
        resume.wait();
        return json{{"answer", 42}};
      });
  EXPECT_EQ(job.state, jobs::JobState::Queued);
  halfway.wait();
  const jobs::JobStatus running = registry.get(job.id);
  EXPECT_EQ(running.state, jobs::JobState::Running);
  EXPECT_EQ(running.stage, "unplanned");
  EXPECT_DOUBLE_EQ(running.progress, 0.25 + 0.75 * 0.5);
  resume.open();
  const jobs::JobStatus done = waitFinal(registry, job.id);
  EXPECT_EQ(done.state, jobs::JobState::Succeeded);
  EXPECT_EQ(done.progress, 1);
  EXPECT_EQ(done.result, json({{"answer", 42}}));
  const json wire = jobs::toJson(done);
  EXPECT_EQ(wire.at("state"), "succeeded");
  EXPECT_TRUE(wire.at("error").is_null());
  EXPECT_TRUE(wire.at("finished_at").is_string());
  EXPECT_EQ(codeOf([&] { registry.cancel(job.id); }), ErrorCode::Conflict);
  EXPECT_EQ(codeOf([&] { registry.get("nope"); }), ErrorCode::NotFound);
  pool.join();
}

TEST(JobRegistry, CancelStopsQueuedJobsAtOnceAndRunningOnesAtTheirNextCheck) {
  exec::WorkPool pool("jobs", 1);
  exec::WorkPool helpers("job-helpers", 1);
  jobs::JobRegistry registry(pool, helpers);
  Gate started;
  std::atomic<bool> secondRan{false};
  const auto first = registry.submit("test", json::object(), {}, [&](jobs::JobContext& context) {
    started.open();
    while (true) {
      context.throwIfCancelled();
      std::this_thread::sleep_for(1ms);
    }
    return json();
  });
  const auto second = registry.submit("test", json::object(), {}, [&](jobs::JobContext&) {
    secondRan = true;
    return json();
  });
  started.wait();
  const auto queued = registry.cancel(second.id);
  EXPECT_EQ(queued.state, jobs::JobState::Cancelled);
  const auto running = registry.cancel(first.id);
  EXPECT_EQ(running.state, jobs::JobState::Running);
  EXPECT_TRUE(running.cancelRequested);
  const auto done = waitFinal(registry, first.id);
  EXPECT_EQ(done.state, jobs::JobState::Cancelled);
  EXPECT_EQ(done.errorCode, ErrorCode::Cancelled);
  pool.join();
  EXPECT_FALSE(secondRan);
  EXPECT_EQ(registry.counts().at(jobs::JobState::Cancelled), 2u);
}

TEST(JobRegistry, FailuresKeepTheirCodeAndTheQueueIsBounded) {
  exec::WorkPool pool("jobs", 1);
  exec::WorkPool helpers("job-helpers", 1);
  jobs::JobRegistry registry(pool, helpers, {.active = 2, .finished = 1, .node = {}});
  Gate gate;
  const auto failing = registry.submit("test", json::object(), {}, [&](jobs::JobContext&) -> json {
    gate.wait();
    throw Error(ErrorCode::InvalidArgument, "bad input");
  });
  const auto second =
      registry.submit("test", json::object(), {}, [](jobs::JobContext&) { return json::object(); });
  EXPECT_EQ(codeOf([&] {
              registry.submit("test", json::object(), {}, [](jobs::JobContext&) { return json(); });
            }),
            ErrorCode::Unavailable);
  gate.open();
  EXPECT_EQ(waitFinal(registry, second.id).state, jobs::JobState::Succeeded);
  // Only the newest finished job is remembered.
  EXPECT_EQ(codeOf([&] { registry.get(failing.id); }), ErrorCode::NotFound);
  registry.cancelAll();
  EXPECT_EQ(codeOf([&] {
              registry.submit("test", json::object(), {}, [](jobs::JobContext&) { return json(); });
            }),
            ErrorCode::Unavailable);
  pool.join();
}

TEST(JobRegistry, InAClusterJobIdsNameTheNodeAndALostLeaseCancelsButStillTakesJobs) {
  exec::WorkPool pool("jobs", 1);
  exec::WorkPool helpers("job-helpers", 1);
  jobs::JobRegistry registry(pool, helpers, {.active = 4, .finished = 4, .node = "n2"});
  Gate gate;
  const auto running = registry.submit("test", json::object(), {}, [&](jobs::JobContext& context) {
    gate.wait();
    context.throwIfCancelled();
    return json::object();
  });
  EXPECT_TRUE(running.id.starts_with("n2-")) << running.id;
  registry.cancelAll(/*refuseNew=*/false);
  gate.open();
  EXPECT_EQ(waitFinal(registry, running.id).state, jobs::JobState::Cancelled);
  const auto next =
      registry.submit("test", json::object(), {}, [](jobs::JobContext&) { return json::object(); });
  EXPECT_EQ(waitFinal(registry, next.id).state, jobs::JobState::Succeeded);
  pool.join();
}

// A job's tasks that are held up (a stalled disk) hold its own thread and the helpers, never a
// thread of the job pool another job needs: with them held, the next job runs and ends.
TEST(JobRegistry, AJobsHeldTasksHoldNoThreadAnotherJobNeeds) {
  exec::WorkPool pool("jobs", 2);
  exec::WorkPool helpers("job-helpers", 1);
  jobs::JobRegistry registry(pool, helpers);
  std::mutex mutex;
  std::condition_variable cv;
  int held = 0;
  bool released = false;
  auto hold = [&] {
    std::unique_lock lock(mutex);
    ++held;
    cv.notify_all();
    cv.wait(lock, [&] { return released; });
  };
  const auto stalled = registry.submit("test", json::object(), {}, [&](jobs::JobContext& context) {
    context.executor().runAll({hold, hold});
    return json::object();
  });
  {
    // A bound, not a wait for time to pass: both tasks start at once on an idle helper.
    std::unique_lock lock(mutex);
    ASSERT_TRUE(cv.wait_for(lock, 60s, [&] { return held == 2; }));
  }
  const auto next =
      registry.submit("test", json::object(), {}, [](jobs::JobContext&) { return json::object(); });
  EXPECT_EQ(waitFinal(registry, next.id).state, jobs::JobState::Succeeded);
  EXPECT_EQ(registry.get(stalled.id).state, jobs::JobState::Running);
  {
    const std::lock_guard lock(mutex);
    released = true;
  }
  cv.notify_all();
  EXPECT_EQ(waitFinal(registry, stalled.id).state, jobs::JobState::Succeeded);
  pool.join();
  helpers.join();
}

// ---- the jobs' executor -----------------------------------------------------------------------

// An operation's tasks run on the caller's thread and on the pool's free ones at once. Two tasks
// that each wait for the other to have started can only finish on two threads.
TEST(PoolExecutor, RunsTasksOnTheCallersThreadAndOnAFreeThreadOfThePoolAtOnce) {
  exec::WorkPool pool("jobs", 2);
  std::atomic<int> helperStarts{0};
  exec::PoolExecutor executor(pool, 1, [&] { ++helperStarts; });
  std::mutex mutex;
  std::condition_variable cv;
  int started = 0;
  std::set<std::thread::id> threads;
  bool bothStarted = true;
  auto meet = [&] {
    std::unique_lock lock(mutex);
    ++started;
    threads.insert(std::this_thread::get_id());
    cv.notify_all();
    // A bound, not a wait for time to pass: on one thread this would never be met.
    bothStarted = cv.wait_for(lock, 60s, [&] { return started == 2; }) && bothStarted;
  };
  Gate done;
  pool.post([&] {  // the job: on a thread of the pool, as JobRegistry runs it
    executor.runAll({meet, meet});
    done.open();
  });
  done.wait();
  EXPECT_TRUE(bothStarted);
  EXPECT_EQ(threads.size(), 2u);
  EXPECT_EQ(helperStarts.load(), 1);
}

// With every thread of the pool taken, the caller runs every task itself: it never waits for a
// helper still queued (no deadlock), and the helper, once it runs, finds nothing left to do.
TEST(PoolExecutor, WithThePoolBusyTheCallerRunsEveryTaskAndALateHelperDoesNothing) {
  exec::WorkPool pool("jobs", 1);
  std::atomic<int> helperStarts{0};
  exec::PoolExecutor executor(pool, 3, [&] { ++helperStarts; });
  Gate release;
  Gate done;
  std::set<std::thread::id> threads;
  std::thread::id jobThread;
  pool.post([&] {
    jobThread = std::this_thread::get_id();
    std::vector<std::function<void()>> tasks(
        5, [&] { threads.insert(std::this_thread::get_id()); });  // one thread: no race
    executor.runAll(std::move(tasks));
    done.open();
    release.wait();
  });
  done.wait();
  EXPECT_EQ(threads, std::set<std::thread::id>{jobThread});
  release.open();
  pool.join();  // the queued helpers run now
  EXPECT_EQ(helperStarts.load(), 0);
}

// Every task runs even when some throw; the first exception is rethrown after all have finished.
TEST(PoolExecutor, RethrowsTheFirstFailureAfterEveryTaskHasRun) {
  exec::WorkPool pool("jobs", 2);
  exec::PoolExecutor executor(pool, 1);
  std::atomic<int> ran{0};
  std::vector<std::function<void()>> tasks;
  for (int i = 0; i < 8; ++i) {
    tasks.push_back([&ran, i] {
      ++ran;
      if (i == 2 || i == 5) {
        throw std::runtime_error("task failed");
      }
    });
  }
  EXPECT_THROW(executor.runAll(std::move(tasks)), std::runtime_error);
  EXPECT_EQ(ran.load(), 8);
  executor.runAll({});  // nothing to run: returns at once
}

}  // namespace
}  // namespace vsm::server
