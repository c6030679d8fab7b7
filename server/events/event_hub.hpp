#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <string_view>

#include <nlohmann/json_fwd.hpp>

namespace vsm::server::http {
class BodyStream;
}

namespace vsm::server::events {

/// Bounds and timings of the event stream (limits.event_subscribers,
/// limits.event_subscribers_per_client and fixed values). The defaults are the daemon's.
struct HubOptions {
  /// Subscribers at once; one more is refused with core::Error(Unavailable) (503, Retry-After).
  std::size_t maxSubscribers = 64;
  /// Subscribers of one client (source address) at once; one more from it is refused like one
  /// over maxSubscribers, while other clients are still taken. Keeps one client from taking every
  /// slot.
  std::size_t maxSubscribersPerClient = 8;
  /// What one subscriber may have queued and not yet taken by its connection: events (heartbeats
  /// count) and their bytes. A subscriber over either is dropped.
  std::size_t queueEvents = 256;
  std::size_t queueBytes = 256 * 1024;
  /// A comment line ": ping" goes to every subscriber this often, so that proxies keep an idle
  /// stream open (and a connection whose peer left notices it at the next write).
  std::chrono::milliseconds heartbeat{15'000};
  /// Progress events of one key (a job) go out at most once per interval; the newest one held
  /// back goes at the end of the interval, those in between never.
  std::chrono::milliseconds progressInterval{250};
  /// The clock (tests pass their own and call tick()).
  std::function<std::chrono::steady_clock::time_point()> now = [] {
    return std::chrono::steady_clock::now();
  };
};

/// The daemon's Server-Sent Events fan-out (GET /v1/events): every event gets the next id of a
/// per-daemon sequence and is serialised once ("id: N\nevent: NAME\ndata: JSON\n\n"), then queued
/// for every subscriber in id order. Subscribers are http::BodyStreams that the connection of each
/// pulls from.
///
/// Bounded: a subscriber holds at most queueEvents events and queueBytes bytes that its connection
/// has not taken (it takes them when its previous write is done, i.e. when the client reads). One
/// more and it is dropped: its queue is replaced by one final "event: dropped" and its stream ends
/// (the connection closes once that is written, or after a moment when the client does not read).
/// Subscribers are capped by maxSubscribers, and those of one client by maxSubscribersPerClient.
/// The hub never blocks on a subscriber.
///
/// Thread-safe: events come from job threads and the registry; streams are pulled on network
/// threads. Lock order: the hub's mutex, then a subscriber's (never the other way round); no lock
/// is held while logging.
class EventHub {
 public:
  using Clock = std::chrono::steady_clock;

  explicit EventHub(HubOptions options = {});
  /// close(), and joins the ticker thread when start() was called.
  ~EventHub();
  EventHub(const EventHub&) = delete;
  EventHub& operator=(const EventHub&) = delete;

  /// Starts the thread that calls tick() (held-back progress, heartbeats) every 50 ms.
  void start();

  /// A new subscriber of `client` (the source address it is counted under); it sees every event
  /// sent from now on. Throws core::Error(Unavailable) when maxSubscribers are subscribed,
  /// `client` has maxSubscribersPerClient, or the hub is closed. The subscription ends when the
  /// stream is stopped or destroyed.
  std::shared_ptr<http::BodyStream> subscribe(const std::string& client = {});

  /// Sends `event` (a name: [a-z_]+) with `data` (a JSON object, written on one line) now.
  void publish(std::string_view event, const nlohmann::json& data);

  /// Sends a progress event of `key` (a job id), coalesced per key: now when the last one of
  /// `key` went out progressInterval ago or longer, else held back (replacing one held back
  /// before) until tick() finds the interval over.
  void progress(const std::string& key, std::string_view event, const nlohmann::json& data);

  /// Forgets `key`'s held-back progress (its job ended: the end event follows, nothing after it).
  void settle(const std::string& key);

  /// Sends held-back progress whose interval is over and, when due, a heartbeat.
  void tick();

  /// Ends every stream (what they queued is still written) and refuses new subscribers. The
  /// ticker thread stops. Idempotent.
  void close();

  /// Subscribers now.
  std::size_t subscribers() const;
  /// Subscribers dropped for falling behind, since the start.
  std::uint64_t dropped() const;
  /// The id the last event got (0 before the first).
  std::uint64_t lastId() const;

  struct State;  // shared with the subscribers; defined in the .cpp

 private:
  std::shared_ptr<State> state_;
};

}  // namespace vsm::server::events
