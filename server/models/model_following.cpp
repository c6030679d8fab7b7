// ModelRegistry's following of other writers' publishes (follow(), reopen(), the swap of an
// opening that setWriter() shares, the announcement of a followed version) and its fencing-token
// bookkeeping: model_following.hpp says what is here and why. The opening, roles, leases and
// lookups are in model_registry.cpp.
#include "server/models/model_following.hpp"

#include <algorithm>
#include <chrono>
#include <exception>
#include <memory>
#include <mutex>
#include <string>
#include <utility>

#include "core/common/log.hpp"
#include "core/store/live_model.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"

namespace vsm::server::models {

namespace log = core::log;

std::uint64_t takeoverOf(const core::LiveModel& live) {
  const auto& fence = live.snapshot()->revision.fence;
  return fence ? fence->takeover : 0;
}

// ---- TakeoverBook ----------------------------------------------------------------------------

std::uint64_t TakeoverBook::newest(std::string_view id, const core::LiveModel& live) const {
  const auto it = seen_.find(id);
  return std::max(it == seen_.end() ? 0 : it->second, takeoverOf(live));
}

void TakeoverBook::saw(std::string_view id, const core::LiveModel& live) {
  if (const std::uint64_t takeover = takeoverOf(live)) {
    auto [it, added] = seen_.try_emplace(std::string(id), takeover);
    it->second = std::max(it->second, takeover);
  }
}

// ---- FollowSchedule --------------------------------------------------------------------------

bool FollowSchedule::waiting(std::string_view id, Clock::time_point now) const {
  const auto it = retry_.find(id);
  return it != retry_.end() && now < it->second;
}

bool FollowSchedule::refusedAsIs(std::string_view id, const Stamp& stamp) const {
  const auto it = refusedStamps_.find(id);
  return it != refusedStamps_.end() && it->second == stamp;
}

void FollowSchedule::followed(std::string_view id) {
  if (const auto it = retry_.find(id); it != retry_.end()) {
    retry_.erase(it);
  }
  if (const auto it = refusedStamps_.find(id); it != refusedStamps_.end()) {
    refusedStamps_.erase(it);
  }
}

void FollowSchedule::refused(std::string_view id, const Stamp& stamp) {
  refusedStamps_.insert_or_assign(std::string(id), stamp);
}

void FollowSchedule::failed(std::string_view id, Clock::time_point retry) {
  retry_.insert_or_assign(std::string(id), retry);
}

// ---- ModelRegistry: following ----------------------------------------------------------------

void ModelRegistry::announceFollowed(const core::LiveModel& old,
                                     const core::LiveModel& fresh) const {
  if (!onPublished_) {
    return;
  }
  const auto before = old.snapshot();
  const auto after = fresh.snapshot();
  if (after->version == before->version) {
    return;  // the same version (read again after a failed write, a change of role)
  }
  // What the other writer changed, as the writer's own publication names it: every patch stored
  // differently, and every patch gone (a restore removes what the restored revision lacks). One
  // walk of both versions in key order.
  core::ModelChange change = core::changeSince(before->model, *after);
  Publication publication;
  publication.model = fresh.name();
  publication.version = after->version;
  publication.followed = true;
  publication.changed = std::move(change.changed);
  publication.removed = std::move(change.removed);
  onPublished_(publication);
}

void ModelRegistry::reopen(std::string_view id) {
  if (const auto version = replace(get(id), id, "after a failed write")) {
    log::warn("model=" + std::string(id) + " read again from disk after a failed write: version " +
              std::to_string(*version));
  }
}

std::optional<std::uint64_t> ModelRegistry::replace(const std::shared_ptr<core::LiveModel>& old,
                                                    std::string_view id, std::string_view why,
                                                    bool* refused) {
  Served fresh;
  try {
    fresh.live = old->reopen();
  } catch (const std::exception& e) {
    log::error("model=" + std::string(id) + " cannot be read again from disk " + std::string(why) +
               ": " + e.what());
    return std::nullopt;
  }
  if (refused != nullptr) {
    const std::uint64_t takeover = takeoverOf(*fresh.live);
    std::uint64_t seen = 0;
    {
      const std::lock_guard lock(mutex_);
      seen = takeovers_.newest(id, *old);
    }
    if (takeover != 0 && takeover < seen) {
      ++followsRefused_;
      log::warn("model=" + std::string(id) + " version " +
                std::to_string(fresh.live->snapshot()->version) +
                " on disk is not followed: its writer's fencing token (takeover " +
                std::to_string(takeover) + ") is older than one already seen (" +
                std::to_string(seen) + "), so a writer that had lost the model committed it; " +
                "version " + std::to_string(old->snapshot()->version) + " stays served");
      *refused = true;
      return std::nullopt;
    }
  }
  try {
    fresh.encoded = EncodedCache::create(cache_, *fresh.live);
    watch(*fresh.live);
  } catch (const std::exception& e) {
    log::error("model=" + std::string(id) + " cannot be read again from disk " + std::string(why) +
               ": " + e.what());
    return std::nullopt;
  }
  const std::uint64_t version = fresh.live->snapshot()->version;
  if (!swapOpening(id, old, std::move(fresh))) {
    return std::nullopt;  // closed or replaced meanwhile
  }
  return version;
}

bool ModelRegistry::swapOpening(std::string_view id, const std::shared_ptr<core::LiveModel>& old,
                                Served fresh) {
  const std::shared_ptr<core::LiveModel> live = fresh.live;
  Served replaced;
  {
    const std::lock_guard lock(mutex_);
    const auto it = models_.find(id);
    if (it == models_.end() || it->second.live != old) {
      return false;
    }
    takeovers_.saw(id, *old);
    takeovers_.saw(id, *live);
    replaced = std::exchange(it->second, std::move(fresh));
  }
  announceFollowed(*old, *live);
  return true;  // `replaced` goes here, outside the lock
}

std::size_t ModelRegistry::follow() {
  std::vector<std::pair<std::string, std::shared_ptr<core::LiveModel>>> readOnly;
  {
    const std::lock_guard lock(mutex_);
    for (const auto& [id, served] : models_) {
      if (!served.live->writable()) {
        readOnly.emplace_back(id, served.live);
      }
    }
  }
  const auto now = std::chrono::steady_clock::now();
  std::size_t followed = 0;
  for (const auto& [id, live] : readOnly) {
    if (followSchedule_.waiting(id, now)) {
      continue;  // its last reading failed: retried a little later, not at every look
    }
    if (!live->changedOnDisk()) {
      continue;
    }
    const std::optional<core::HierarchyStamp> stamp = core::hierarchyStamp(live->dir());
    if (followSchedule_.refusedAsIs(id, stamp)) {
      continue;  // refused as it is (a stale fencing token): read again once it changes
    }
    bool refused = false;
    const auto start = std::chrono::steady_clock::now();
    if (const auto version = replace(live, id, "after another writer published", &refused)) {
      log::info("model=" + id + " read again from disk after another writer published: version " +
                std::to_string(*version) + " (" +
                std::to_string(std::chrono::duration_cast<std::chrono::milliseconds>(
                                   std::chrono::steady_clock::now() - start)
                                   .count()) +
                " ms)");
      ++followed;
      followSchedule_.followed(id);
    } else if (refused) {
      followSchedule_.refused(id, stamp);
    } else {
      followSchedule_.failed(id, now + kFollowRetry);
    }
  }
  return followed;
}

}  // namespace vsm::server::models
