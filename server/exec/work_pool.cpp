#include "server/exec/work_pool.hpp"

#include <algorithm>
#include <exception>
#include <mutex>

#include <boost/asio/post.hpp>
#include <boost/asio/thread_pool.hpp>

#include "core/common/log.hpp"

namespace vsm::server::exec {

struct WorkPool::Impl {
  explicit Impl(std::size_t threads) : pool(threads) {}
  boost::asio::thread_pool pool;
  std::once_flag joined;
};

WorkPool::WorkPool(std::string name, std::size_t threads)
    : name_(std::move(name)),
      threads_(std::max<std::size_t>(threads, 1)),
      impl_(std::make_unique<Impl>(threads_)) {}

WorkPool::~WorkPool() {
  join();
}

void WorkPool::post(std::function<void()> task) {
  queued_.fetch_add(1, std::memory_order_relaxed);
  boost::asio::post(impl_->pool, [this, task = std::move(task)]() {
    queued_.fetch_sub(1, std::memory_order_relaxed);
    active_.fetch_add(1, std::memory_order_relaxed);
    try {
      task();
    } catch (const std::exception& e) {
      core::log::error("pool=" + name_ + " task threw (a bug): " + e.what());
    } catch (...) {
      core::log::error("pool=" + name_ + " task threw a non-exception (a bug)");
    }
    active_.fetch_sub(1, std::memory_order_relaxed);
  });
}

void WorkPool::join() {
  std::call_once(impl_->joined, [this] { impl_->pool.join(); });
}

}  // namespace vsm::server::exec
