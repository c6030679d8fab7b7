#pragma once

// Following: how a node keeps up with the versions another writer publishes into a model it only
// reads, and refuses a version committed under a stale fencing token. ModelRegistry does it
// (follow(), and the swap of an opening that reopen() and setWriter() share, in
// model_following.cpp); this header holds what it remembers for that, which needs none of the
// registry's tables.

#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <optional>
#include <string>
#include <string_view>

#include "core/opc/opc_reader.hpp"

namespace vsm::core {
class LiveModel;
}  // namespace vsm::core

namespace vsm::server::models {

/// The fencing token (takeover) of `live`'s current version; 0 when it has none.
std::uint64_t takeoverOf(const core::LiveModel& live);

/// The newest fencing token seen per model id, over every opening of the model (its own publishes
/// included). Not synchronised: ModelRegistry guards it with its mutex.
class TakeoverBook {
 public:
  /// The newest token seen for `id`, `live`'s current version included.
  std::uint64_t newest(std::string_view id, const core::LiveModel& live) const;
  /// Remembers the token of `live`'s current version as seen for `id`.
  void saw(std::string_view id, const core::LiveModel& live);

 private:
  std::map<std::string, std::uint64_t, std::less<>> seen_;
};

/// ModelRegistry::follow()'s own memory, for its one caller at a time: the models whose reading
/// failed, tried again only after a while, and the hierarchy files it refused (a stale fencing
/// token), as they were then.
class FollowSchedule {
 public:
  using Clock = std::chrono::steady_clock;
  using Stamp = std::optional<core::HierarchyStamp>;

  /// True while `id`'s last reading failed less than its retry ago (failed()).
  bool waiting(std::string_view id, Clock::time_point now) const;
  /// True when `stamp` is the hierarchy file of `id` refused last: read again once it changes.
  bool refusedAsIs(std::string_view id, const Stamp& stamp) const;

  /// `id` was read again: nothing is remembered of it.
  void followed(std::string_view id);
  /// The version of `id` whose hierarchy file is `stamp` was refused.
  void refused(std::string_view id, const Stamp& stamp);
  /// Reading `id` again failed: tried again at `retry`.
  void failed(std::string_view id, Clock::time_point retry);

 private:
  std::map<std::string, Clock::time_point, std::less<>> retry_;
  std::map<std::string, Stamp, std::less<>> refusedStamps_;
};

}  // namespace vsm::server::models
