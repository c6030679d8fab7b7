// Lock order: State::mutex, then Subscriber::mutex_. A subscriber's wake function is called under
// its own mutex: it only posts to the connection's strand and never calls back into the hub.
#include "server/events/event_hub.hpp"

#include <condition_variable>
#include <deque>
#include <map>
#include <mutex>
#include <optional>
#include <thread>
#include <utility>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "server/http/message.hpp"

namespace vsm::server::events {

using core::Error;
using core::ErrorCode;
using Clock = EventHub::Clock;
using Frame = std::shared_ptr<const std::string>;

namespace {

/// How often the ticker thread calls tick().
constexpr std::chrono::milliseconds kTickEvery{50};

class Subscriber;

}  // namespace

struct EventHub::State {
  explicit State(HubOptions o) : options(std::move(o)) {}

  /// Appends `frame` to every subscriber's queue, dropping those it overflows. Under `mutex`.
  void deliverLocked(const Frame& frame, std::vector<std::string>* notices);
  /// One subscriber of `client` fewer. Under `mutex`.
  void forgetClientLocked(const std::string& client) {
    if (const auto it = perClient.find(client); it != perClient.end() && --it->second == 0) {
      perClient.erase(it);
    }
  }
  /// Serialises an event with the next id and delivers it. Under `mutex`.
  void emitLocked(std::string_view event, const nlohmann::json& data,
                  std::vector<std::string>* notices);

  const HubOptions options;
  mutable std::mutex mutex;              // guards everything below
  std::vector<Subscriber*> subscribers;  // they remove themselves when stopped or destroyed
  /// Subscribers per client; clients with none are not kept.
  std::map<std::string, std::size_t, std::less<>> perClient;
  std::uint64_t nextId = 1;
  std::uint64_t dropped = 0;
  std::uint64_t subscribed = 0;  // ever, for their names in the log
  bool closed = false;
  Clock::time_point lastHeartbeat;
  struct Held {
    Clock::time_point lastSent;
    std::optional<std::pair<std::string, nlohmann::json>> waiting;
  };
  std::map<std::string, Held, std::less<>> progress;
  // The ticker thread.
  std::condition_variable wakeTicker;
  std::thread ticker;
};

namespace {

void logNotices(const std::vector<std::string>& notices) {
  for (const std::string& notice : notices) {
    core::log::warn(notice);
  }
}

/// One subscriber's stream: a bounded queue of frames shared with the other subscribers.
class Subscriber final : public http::BodyStream {
 public:
  Subscriber(std::shared_ptr<EventHub::State> hub, std::uint64_t number, std::string client)
      : hub_(std::move(hub)), number_(number), client_(std::move(client)) {}
  ~Subscriber() override { leave(); }

  void start(std::function<void()> wake) override {
    const std::lock_guard lock(mutex_);
    wake_ = std::move(wake);
    if (!queue_.empty() || ended_) {
      woken_ = true;
      wake_();
    }
  }

  bool pull(std::string& out) override {
    const std::lock_guard lock(mutex_);
    woken_ = false;
    out.reserve(bytes_);
    for (const Frame& frame : queue_) {
      out += *frame;
    }
    queue_.clear();
    bytes_ = 0;
    return !ended_;
  }

  bool ended() const override {
    const std::lock_guard lock(mutex_);
    return ended_;
  }

  void stop() noexcept override {
    {
      const std::lock_guard lock(mutex_);
      wake_ = nullptr;
      ended_ = true;
      queue_.clear();
      bytes_ = 0;
    }
    leave();
  }

  /// Queues `frame`; false when it does not fit (then the caller drops this subscriber). Called
  /// under the hub's mutex.
  bool push(const Frame& frame) {
    const std::lock_guard lock(mutex_);
    if (ended_) {
      return true;
    }
    const std::size_t limitEvents = hub_->options.queueEvents;
    const std::size_t limitBytes = hub_->options.queueBytes;
    if (queue_.size() + 1 > limitEvents || bytes_ + frame->size() > limitBytes) {
      return false;
    }
    queue_.push_back(frame);
    bytes_ += frame->size();
    wakeLocked();
    return true;
  }

  /// Ends the stream: with `last`, the queue is replaced by it (a drop); without, what is queued
  /// is still taken (close). Called under the hub's mutex. Returns what was queued (events,
  /// bytes), for the log.
  std::pair<std::size_t, std::size_t> end(const Frame& last) {
    const std::lock_guard lock(mutex_);
    const std::pair<std::size_t, std::size_t> queued{queue_.size(), bytes_};
    if (last) {
      queue_.clear();
      queue_.push_back(last);
      bytes_ = last->size();
    }
    ended_ = true;
    // Always, even when woken already: a connection whose write is stuck took its last wake
    // while writing, and must hear of the end now (it then closes soon; see BodyStream::ended).
    woken_ = true;
    if (wake_) {
      wake_();
    }
    return queued;
  }

  std::uint64_t number() const { return number_; }

  const std::string& client() const { return client_; }

  /// Called by the hub, under its mutex, once it forgot this subscriber (it is off the list and
  /// no longer counted for its client).
  void forgotten() { listed_ = false; }

 private:
  void wakeLocked() {
    if (!woken_ && wake_) {
      woken_ = true;
      wake_();
    }
  }

  /// Leaves the hub's list (once; the hub's mutex is taken, not ours).
  void leave() noexcept {
    const std::lock_guard lock(hub_->mutex);
    if (!listed_) {
      return;
    }
    listed_ = false;
    auto& list = hub_->subscribers;
    std::erase(list, this);
    hub_->forgetClientLocked(client_);
  }

  const std::shared_ptr<EventHub::State> hub_;
  const std::uint64_t number_;
  const std::string client_;
  bool listed_ = true;  // guarded by the hub's mutex

  mutable std::mutex mutex_;  // guards everything below
  std::deque<Frame> queue_;
  std::size_t bytes_ = 0;
  bool ended_ = false;
  bool woken_ = false;  // wake_ was called and pull() has not run since
  std::function<void()> wake_;
};

Frame serialise(std::uint64_t id, std::string_view event, const nlohmann::json& data) {
  // dump() escapes control characters, so the JSON is one line: one "data:" field.
  std::string text = "id: " + std::to_string(id) + "\nevent: ";
  text += event;
  text += "\ndata: ";
  text += data.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
  text += "\n\n";
  return std::make_shared<const std::string>(std::move(text));
}

}  // namespace

void EventHub::State::deliverLocked(const Frame& frame, std::vector<std::string>* notices) {
  for (auto it = subscribers.begin(); it != subscribers.end();) {
    Subscriber& subscriber = **it;
    if (subscriber.push(frame)) {
      ++it;
      continue;
    }
    // Fell behind: one final event instead of everything queued, then the stream ends.
    const nlohmann::json why = {
        {"reason", "queue_full"},
        {"message",
         "this subscriber did not read its events fast enough and was dropped; "
         "reconnect and re-read the state (GET /v1/jobs, /v1/models)"},
        {"queue_events", options.queueEvents},
        {"queue_bytes", options.queueBytes},
    };
    const Frame last =
        std::make_shared<const std::string>("event: dropped\ndata: " + why.dump() + "\n\n");
    const auto [events, bytes] = subscriber.end(last);
    ++dropped;
    notices->push_back("events: subscriber " + std::to_string(subscriber.number()) +
                       " dropped: it fell behind (" + std::to_string(events) + " events, " +
                       std::to_string(bytes) + " bytes queued; limits " +
                       std::to_string(options.queueEvents) + " events, " +
                       std::to_string(options.queueBytes) + " bytes)");
    subscriber.forgotten();
    forgetClientLocked(subscriber.client());
    it = subscribers.erase(it);
  }
}

void EventHub::State::emitLocked(std::string_view event, const nlohmann::json& data,
                                 std::vector<std::string>* notices) {
  deliverLocked(serialise(nextId++, event, data), notices);
}

EventHub::EventHub(HubOptions options) : state_(std::make_shared<State>(std::move(options))) {
  state_->lastHeartbeat = state_->options.now();
}

EventHub::~EventHub() {
  close();
}

void EventHub::start() {
  const std::lock_guard lock(state_->mutex);
  if (state_->ticker.joinable() || state_->closed) {
    return;
  }
  state_->ticker = std::thread([this] {
    std::unique_lock lock(state_->mutex);
    while (!state_->closed) {
      state_->wakeTicker.wait_for(lock, kTickEvery);
      if (state_->closed) {
        break;
      }
      lock.unlock();
      tick();
      lock.lock();
    }
  });
}

std::shared_ptr<http::BodyStream> EventHub::subscribe(const std::string& client) {
  std::shared_ptr<Subscriber> subscriber;
  std::size_t count = 0;
  {
    const std::lock_guard lock(state_->mutex);
    if (state_->closed) {
      throw Error(ErrorCode::Unavailable, "the daemon is stopping");
    }
    if (state_->subscribers.size() >= state_->options.maxSubscribers) {
      throw Error(ErrorCode::Unavailable,
                  "the event stream has " + std::to_string(state_->options.maxSubscribers) +
                      " subscribers, its limit (limits.event_subscribers); retry shortly");
    }
    std::size_t& mine = state_->perClient[client];
    if (mine >= state_->options.maxSubscribersPerClient) {
      if (mine == 0) {
        state_->perClient.erase(client);
      }
      throw Error(ErrorCode::Unavailable,
                  "this client address has " +
                      std::to_string(state_->options.maxSubscribersPerClient) +
                      " event subscribers, its limit (limits.event_subscribers_per_client); "
                      "retry shortly");
    }
    subscriber = std::make_shared<Subscriber>(state_, ++state_->subscribed, client);
    state_->subscribers.push_back(subscriber.get());
    ++mine;
    count = state_->subscribers.size();
  }
  core::log::info("events: subscriber " + std::to_string(subscriber->number()) + " joined (" +
                  std::to_string(count) + " now)");
  return subscriber;
}

void EventHub::publish(std::string_view event, const nlohmann::json& data) {
  std::vector<std::string> notices;
  {
    const std::lock_guard lock(state_->mutex);
    if (state_->closed) {
      return;
    }
    state_->emitLocked(event, data, &notices);
  }
  logNotices(notices);
}

void EventHub::progress(const std::string& key, std::string_view event,
                        const nlohmann::json& data) {
  std::vector<std::string> notices;
  {
    const std::lock_guard lock(state_->mutex);
    if (state_->closed) {
      return;
    }
    const Clock::time_point now = state_->options.now();
    const auto [it, fresh] = state_->progress.try_emplace(key);
    State::Held& held = it->second;
    if (fresh || now - held.lastSent >= state_->options.progressInterval) {
      held.lastSent = now;
      held.waiting.reset();
      state_->emitLocked(event, data, &notices);
    } else {
      held.waiting.emplace(std::string(event), data);
    }
  }
  logNotices(notices);
}

void EventHub::settle(const std::string& key) {
  const std::lock_guard lock(state_->mutex);
  state_->progress.erase(key);
}

void EventHub::tick() {
  std::vector<std::string> notices;
  {
    const std::lock_guard lock(state_->mutex);
    if (state_->closed) {
      return;
    }
    const Clock::time_point now = state_->options.now();
    const auto interval = state_->options.progressInterval;
    for (auto it = state_->progress.begin(); it != state_->progress.end();) {
      State::Held& held = it->second;
      if (held.waiting && now - held.lastSent >= interval) {
        held.lastSent = now;
        state_->emitLocked(held.waiting->first, held.waiting->second, &notices);
        held.waiting.reset();
      }
      // A key quiet for long is forgotten (a job whose end was never settled): the map stays
      // as small as the jobs that report.
      if (!held.waiting && now - held.lastSent >= 40 * interval) {
        it = state_->progress.erase(it);
      } else {
        ++it;
      }
    }
    if (now - state_->lastHeartbeat >= state_->options.heartbeat) {
      state_->lastHeartbeat = now;
      static const Frame ping = std::make_shared<const std::string>(": ping\n\n");
      state_->deliverLocked(ping, &notices);
    }
  }
  logNotices(notices);
}

void EventHub::close() {
  std::thread ticker;
  {
    const std::lock_guard lock(state_->mutex);
    if (!state_->closed) {
      state_->closed = true;
      for (Subscriber* subscriber : state_->subscribers) {
        subscriber->end(nullptr);
        subscriber->forgotten();
      }
      state_->subscribers.clear();
      state_->perClient.clear();
      state_->progress.clear();
    }
    ticker = std::move(state_->ticker);
  }
  state_->wakeTicker.notify_all();
  if (ticker.joinable()) {
    ticker.join();
  }
}

std::size_t EventHub::subscribers() const {
  const std::lock_guard lock(state_->mutex);
  return state_->subscribers.size();
}

std::uint64_t EventHub::dropped() const {
  const std::lock_guard lock(state_->mutex);
  return state_->dropped;
}

std::uint64_t EventHub::lastId() const {
  const std::lock_guard lock(state_->mutex);
  return state_->nextId - 1;
}

}  // namespace vsm::server::events
