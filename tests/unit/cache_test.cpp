#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <map>
#include <mutex>
#include <random>
#include <set>
#include <thread>
#include <vector>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"

namespace vsm::core {
namespace {

constexpr std::size_t kMiB = 1024 * 1024;

/// An object as the cache sees it: `bytes` of payload whose first word is a version number.
using Blob = std::vector<std::uint64_t>;

std::shared_ptr<const Blob> makeBlob(std::size_t bytes, std::uint64_t version) {
  auto blob = std::make_shared<Blob>(bytes / sizeof(std::uint64_t), version);
  return blob;
}

/// A store over "disk" kept in memory: every key has a size and a stored version. Counts loads
/// and write-backs and checks that no key is loaded or written twice at the same time.
class FakeStore final : public PatchStore {
 public:
  FakeStore(int patches, std::size_t bytesEach) : bytesEach_(bytesEach) {
    for (int i = 0; i < patches; ++i) {
      disk_[key(i)] = 1;
    }
  }
  static PatchKey key(int i) { return PatchKey{10, static_cast<std::uint32_t>(i), 0}; }
  /// The cache's id of patch i's positions.
  static ObjectId id(int i, MemoryCategory category = MemoryCategory::Positions) {
    return {key(i), 1, category};
  }

  std::size_t expectedBytes(const ObjectId&) const override { return bytesEach_; }

  CacheValue load(const ObjectId& id) override {
    const PatchKey& k = id.key;
    Busy busy(*this, k);
    std::uint64_t version = 0;
    {
      std::lock_guard lock(mutex_);
      const auto it = disk_.find(k);
      if (it == disk_.end()) {
        throw Error(ErrorCode::NotFound, "no such patch");
      }
      version = it->second;
      ++loads_;
    }
    return {makeBlob(bytesEach_, version), bytesEach_};
  }

  void writeBack(const ObjectId& id, const CacheValue& value) override {
    const PatchKey& k = id.key;
    Busy busy(*this, k);
    if (failWrites_) {
      throw Error(ErrorCode::Io, "disk full");
    }
    if (firstWriteAwaitsCompany_.exchange(false)) {
      // Writers that can run side by side do so here, on any machine: the first write waits
      // until a second one has begun (a bound far above any scheduling delay, for a cache that
      // serialises them: then it goes on alone and mostBusy() says so).
      std::unique_lock lock(mutex_);
      company_.wait_for(lock, std::chrono::seconds(60), [this] { return busy_.size() >= 2; });
    }
    std::this_thread::sleep_for(writeTime_);  // a write's duration, so that flushers overlap
    std::lock_guard lock(mutex_);
    disk_[k] = value.object.as<Blob>()->front();
    ++writes_;
  }

  std::uint64_t stored(const PatchKey& k) {
    std::lock_guard lock(mutex_);
    return disk_.at(k);
  }
  int loads() {
    std::lock_guard lock(mutex_);
    return loads_;
  }
  int writes() {
    std::lock_guard lock(mutex_);
    return writes_;
  }
  bool overlapped() const { return overlapped_.load(); }
  /// The most keys loaded or written at the same time.
  std::size_t mostBusy() {
    std::lock_guard lock(mutex_);
    return mostBusy_;
  }
  std::atomic<bool> failWrites_{false};
  std::chrono::microseconds writeTime_{0};
  /// The next write waits until another load or write is under way (at most a minute).
  std::atomic<bool> firstWriteAwaitsCompany_{false};

 private:
  struct Busy {
    Busy(FakeStore& s, const PatchKey& k) : store(s), key(k) {
      std::lock_guard lock(store.mutex_);
      if (!store.busy_.insert({key.x, key.y}).second) {
        store.overlapped_ = true;
      }
      store.mostBusy_ = std::max(store.mostBusy_, store.busy_.size());
      store.company_.notify_all();
    }
    ~Busy() {
      std::lock_guard lock(store.mutex_);
      store.busy_.erase({key.x, key.y});
    }
    FakeStore& store;
    PatchKey key;
  };

  std::size_t bytesEach_;
  std::mutex mutex_;                 // guards disk_, busy_, loads_, writes_, mostBusy_
  std::condition_variable company_;  // busy_ grew (with mutex_)
  std::map<PatchKey, std::uint64_t> disk_;
  std::set<std::pair<std::uint32_t, std::uint32_t>> busy_;
  int loads_ = 0;
  int writes_ = 0;
  std::size_t mostBusy_ = 0;
  std::atomic<bool> overlapped_{false};
};

std::uint64_t versionOf(const PatchCache::Pin& pin) {
  return pin.get<Blob>()->front();
}

class CachePolicies : public ::testing::TestWithParam<EvictionPolicy> {};

INSTANTIATE_TEST_SUITE_P(Both, CachePolicies,
                         ::testing::Values(EvictionPolicy::FifoSecondChance,
                                           EvictionPolicy::CostAwareClock),
                         [](const auto& info) {
                           return info.param == EvictionPolicy::FifoSecondChance ? "Fifo" : "Clock";
                         });

TEST_P(CachePolicies, ResidentBytesNeverExceedTheBudgetOverModelsFarLargerThanIt) {
  // 16 MiB budget; four models of 64 patches of 792 KiB (a 257 x 257 V3f grid): ~200 MiB.
  constexpr std::size_t kBudget = 16 * kMiB;
  constexpr std::size_t kPatchBytes = 257 * 257 * 12;
  constexpr int kPatches = 64;
  PatchCache cache(kBudget, GetParam());
  std::vector<std::unique_ptr<FakeStore>> stores;
  std::vector<PatchCache::ModelId> models;
  for (int m = 0; m < 4; ++m) {
    stores.push_back(std::make_unique<FakeStore>(kPatches, kPatchBytes));
    models.push_back(cache.addModel("model" + std::to_string(m), *stores.back()));
  }
  // What each patch must read as: bumped by every write below.
  std::vector<std::vector<std::uint64_t>> expected(4, std::vector<std::uint64_t>(kPatches, 1));

  std::mt19937 rng(42);
  std::uniform_int_distribution<int> model(0, 3);
  std::uniform_int_distribution<int> uniform(0, kPatches - 1);
  // Skewed: Zipf-like by squaring a uniform variate.
  std::uniform_real_distribution<double> unit(0, 1);
  for (int op = 0; op < 3000; ++op) {
    const int m = model(rng);
    const int p = op % 2 == 0 ? uniform(rng) : static_cast<int>(std::pow(unit(rng), 3) * kPatches);
    const PatchKey key = FakeStore::key(p);
    if (op % 7 == 0) {
      const std::uint64_t version = ++expected[m][p];
      cache.put(models[m], {key, 1, MemoryCategory::Positions},
                {makeBlob(kPatchBytes, version), kPatchBytes}, true);
    } else {
      const auto pin = cache.get(models[m], {key, 1, MemoryCategory::Positions});
      ASSERT_EQ(versionOf(pin), expected[m][p]) << "model " << m << " patch " << p;
    }
    const CacheStats stats = cache.stats();
    ASSERT_LE(stats.residentBytes, kBudget) << "after operation " << op;
  }
  const CacheStats stats = cache.stats();
  EXPECT_GT(stats.evictions, 100u);
  EXPECT_GT(stats.writeBacks, 0u);
  EXPECT_GT(stats.hits, 0u);
  EXPECT_EQ(stats.pinnedBytes, 0u);
  // The high-water mark: the budget was reached (the cache was full) and never passed.
  EXPECT_LE(stats.peakResidentBytes, kBudget);
  EXPECT_GT(stats.peakResidentBytes, kBudget - kPatchBytes);
  for (int m = 0; m < 4; ++m) {
    cache.removeModel(models[m]);
    for (int p = 0; p < kPatches; ++p) {
      EXPECT_EQ(stores[m]->stored(FakeStore::key(p)), expected[m][p]);
    }
  }
  EXPECT_EQ(cache.stats().residentBytes, 0u);
}

TEST_P(CachePolicies, AnEvictedDirtyPatchReloadsWithItsChanges) {
  FakeStore store(8, kMiB);
  PatchCache cache(2 * kMiB, GetParam());
  const auto model = cache.addModel("m", store);
  cache.put(model, FakeStore::id(0), {makeBlob(kMiB, 7), kMiB}, true);
  for (int i = 1; i < 8; ++i) {
    cache.get(model, FakeStore::id(i));
  }
  EXPECT_FALSE(cache.resident(model, FakeStore::id(0)));
  EXPECT_EQ(store.stored(FakeStore::key(0)), 7u);
  EXPECT_EQ(versionOf(cache.get(model, FakeStore::id(0))), 7u);
  cache.removeModel(model);
}

TEST_P(CachePolicies, PinnedPatchesSurviveEviction) {
  FakeStore store(16, kMiB);
  PatchCache cache(4 * kMiB, GetParam());
  const auto model = cache.addModel("m", store);
  auto held = cache.get(model, FakeStore::id(0));
  for (int round = 0; round < 3; ++round) {
    for (int i = 1; i < 16; ++i) {
      cache.get(model, FakeStore::id(i));
      ASSERT_TRUE(cache.resident(model, FakeStore::id(0)));
    }
  }
  EXPECT_EQ(cache.stats().pinnedBytes, kMiB);
  held = PatchCache::Pin();
  EXPECT_EQ(cache.stats().pinnedBytes, 0u);
  cache.removeModel(model);
}

TEST_P(CachePolicies, AnAllPinnedCacheAnswersResourceExhausted) {
  FakeStore store(4, kMiB);
  PatchCache cache(2 * kMiB, GetParam());
  const auto model = cache.addModel("m", store);
  auto a = cache.get(model, FakeStore::id(0));
  auto b = cache.get(model, FakeStore::id(1));
  try {
    cache.get(model, FakeStore::id(2));
    FAIL() << "no exception";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::ResourceExhausted);
  }
  EXPECT_EQ(cache.stats().exhausted, 1u);
  EXPECT_LE(cache.stats().residentBytes, 2 * kMiB);
  // Releasing one pin makes room again.
  a = PatchCache::Pin();
  EXPECT_NO_THROW(cache.get(model, FakeStore::id(2)));
  b = PatchCache::Pin();
  cache.removeModel(model);
}

TEST(PatchCache, AnObjectLargerThanTheBudgetIsRefused) {
  FakeStore store(1, 3 * kMiB);
  PatchCache cache(2 * kMiB);
  const auto model = cache.addModel("m", store);
  EXPECT_THROW(cache.get(model, FakeStore::id(0)), Error);
  EXPECT_EQ(cache.stats().residentBytes, 0u);
  cache.removeModel(model);
}

TEST(PatchCache, AFailedLoadLeavesNothingCharged) {
  FakeStore store(1, kMiB);
  PatchCache cache(2 * kMiB);
  const auto model = cache.addModel("m", store);
  EXPECT_THROW(cache.get(model, {PatchKey{10, 99, 0}, 1, MemoryCategory::Positions}), Error);
  EXPECT_EQ(cache.stats().residentBytes, 0u);
  cache.removeModel(model);
}

TEST(PatchCache, AFailedWriteBackKeepsThePatchDirtyAndResident) {
  FakeStore store(4, kMiB);
  PatchCache cache(kMiB);
  const auto model = cache.addModel("m", store);
  cache.put(model, FakeStore::id(0), {makeBlob(kMiB, 5), kMiB}, true);
  store.failWrites_ = true;
  EXPECT_THROW(cache.get(model, FakeStore::id(1)), Error);
  EXPECT_TRUE(cache.resident(model, FakeStore::id(0)));
  store.failWrites_ = false;
  EXPECT_NO_THROW(cache.get(model, FakeStore::id(1)));
  EXPECT_EQ(store.stored(FakeStore::key(0)), 5u);
  cache.removeModel(model);
}

TEST(PatchCache, SeveralFlushersWriteEveryDirtyEntryOnceBetweenThem) {
  // A publish's parallel write-back: four threads flush the same model at once.
  constexpr int kPatches = 64;
  FakeStore store(kPatches, 64 * 1024);
  store.writeTime_ = std::chrono::milliseconds(2);
  store.firstWriteAwaitsCompany_ = true;
  PatchCache cache(16 * kMiB);
  const auto model = cache.addModel("m", store);
  for (int i = 0; i < kPatches; ++i) {
    cache.put(model, FakeStore::id(i), {makeBlob(64 * 1024, 100 + i), 64 * 1024}, true);
  }
  {
    std::vector<std::jthread> flushers;
    for (int t = 0; t < 4; ++t) {
      flushers.emplace_back([&] { cache.flush(model); });
    }
  }
  EXPECT_EQ(store.writes(), kPatches);  // each once
  EXPECT_FALSE(store.overlapped());     // never one entry by two flushers
  EXPECT_GT(store.mostBusy(), 1u);      // they did write side by side
  EXPECT_EQ(cache.stats().writeBacks, static_cast<std::uint64_t>(kPatches));
  for (int i = 0; i < kPatches; ++i) {
    EXPECT_EQ(store.stored(FakeStore::key(i)), static_cast<std::uint64_t>(100 + i));
  }
  cache.flush(model);  // nothing is dirty any more
  EXPECT_EQ(store.writes(), kPatches);

  // A failing write-back reaches the flusher that ran it; the entry stays dirty for a retry.
  cache.put(model, FakeStore::id(0), {makeBlob(64 * 1024, 7), 64 * 1024}, true);
  store.failWrites_ = true;
  EXPECT_THROW(cache.flush(model), Error);
  store.failWrites_ = false;
  cache.flush(model);
  EXPECT_EQ(store.stored(FakeStore::key(0)), 7u);
  cache.removeModel(model);
}

TEST(PatchCache, FlushingOneEntryWritesItAloneAndLeavesTheOthersDirty) {
  // A merge stores each finished patch while it computes the next ones.
  FakeStore store(3, kMiB);
  PatchCache cache(8 * kMiB);
  const auto model = cache.addModel("m", store);
  for (int i = 0; i < 3; ++i) {
    cache.put(model, FakeStore::id(i), {makeBlob(kMiB, 20 + i), kMiB}, true);
  }
  cache.flush(model, FakeStore::id(1));
  EXPECT_EQ(store.writes(), 1);
  EXPECT_EQ(store.stored(FakeStore::key(1)), 21u);
  cache.flush(model, FakeStore::id(1));  // clean now: no second write
  cache.flush(model, FakeStore::id(7));  // not resident: nothing
  EXPECT_EQ(store.writes(), 1);
  // A failure reaches the caller and leaves the entry dirty; the model's flush writes the rest.
  cache.put(model, FakeStore::id(1), {makeBlob(kMiB, 31), kMiB}, true);
  store.failWrites_ = true;
  EXPECT_THROW(cache.flush(model, FakeStore::id(1)), Error);
  store.failWrites_ = false;
  cache.flush(model);
  EXPECT_EQ(store.writes(), 4);
  EXPECT_EQ(store.stored(FakeStore::key(0)), 20u);
  EXPECT_EQ(store.stored(FakeStore::key(1)), 31u);
  EXPECT_EQ(store.stored(FakeStore::key(2)), 22u);
  cache.removeModel(model);
}

// A publish flushes its model: the flush writes that model's dirty entries, found among a cache
// full of clean ones and another model's dirty ones, and never an entry invalidated while pinned
// (a discarded value: before, the flush found it in the ring, dirty, and looped on it forever).
TEST(PatchCache, AFlushWritesItsModelsDirtyEntriesOnlyAndNeverAnInvalidatedOne) {
  FakeStore store(8, kMiB);
  FakeStore other(8, kMiB);
  PatchCache cache(64 * kMiB);
  const auto model = cache.addModel("m", store);
  const auto otherModel = cache.addModel("o", other);
  for (int i = 0; i < 8; ++i) {
    cache.get(model, FakeStore::id(i));
    cache.get(otherModel, FakeStore::id(i));
  }
  cache.put(model, FakeStore::id(1), {makeBlob(kMiB, 21), kMiB}, true);
  cache.put(model, FakeStore::id(5), {makeBlob(kMiB, 25), kMiB}, true);
  cache.put(otherModel, FakeStore::id(2), {makeBlob(kMiB, 32), kMiB}, true);
  PatchCache::Pin discarded = cache.put(model, FakeStore::id(6), {makeBlob(kMiB, 26), kMiB}, true);
  cache.invalidate(model, FakeStore::id(6));
  cache.flush(model);
  EXPECT_EQ(store.writes(), 2);
  EXPECT_EQ(store.stored(FakeStore::key(1)), 21u);
  EXPECT_EQ(store.stored(FakeStore::key(5)), 25u);
  EXPECT_EQ(store.stored(FakeStore::key(6)), 1u);
  EXPECT_EQ(other.writes(), 0);
  cache.flush(model);  // nothing dirty any more
  EXPECT_EQ(store.writes(), 2);
  discarded = PatchCache::Pin();
  cache.flush(otherModel);
  EXPECT_EQ(other.writes(), 1);
  EXPECT_EQ(other.stored(FakeStore::key(2)), 32u);
  cache.removeModel(model);
  cache.removeModel(otherModel);
}

TEST(PatchCache, InvalidateServesNewDataWhileOldPinsKeepTheirs) {
  FakeStore store(2, kMiB);
  PatchCache cache(4 * kMiB);
  const auto model = cache.addModel("m", store);
  auto old = cache.get(model, FakeStore::id(0));
  EXPECT_EQ(versionOf(old), 1u);
  // The stored version changes behind the cache (a publish), then the entry is invalidated.
  cache.put(model, FakeStore::id(1), {makeBlob(kMiB, 9), kMiB}, true);
  cache.flush(model);
  cache.invalidate(model, FakeStore::id(0));
  EXPECT_FALSE(cache.resident(model, FakeStore::id(0)));
  EXPECT_EQ(cache.stats().residentBytes, 2 * kMiB);  // the old object is still held
  auto fresh = cache.get(model, FakeStore::id(0));
  EXPECT_EQ(store.loads(), 2);
  EXPECT_EQ(versionOf(old), 1u);
  EXPECT_EQ(cache.stats().residentBytes, 3 * kMiB);
  old = PatchCache::Pin();
  EXPECT_EQ(cache.stats().residentBytes, 2 * kMiB);
  fresh = PatchCache::Pin();
  cache.removeModel(model);
}

TEST(PatchCache, FindNeverLoadsAndPinsWhatItFinds) {
  FakeStore store(8, kMiB);
  PatchCache cache(2 * kMiB);
  const auto model = cache.addModel("m", store);
  // A miss: nothing loaded, one miss counted (none with countMiss false: a second look).
  EXPECT_FALSE(cache.find(model, FakeStore::id(0)));
  EXPECT_FALSE(cache.find(model, FakeStore::id(0), /*countMiss=*/false));
  EXPECT_EQ(store.loads(), 0);
  EXPECT_EQ(cache.stats().misses, 1u);
  EXPECT_FALSE(cache.resident(model, FakeStore::id(0)));

  cache.get(model, FakeStore::id(0));  // loads (a second miss), then unpinned
  const auto hitsBefore = cache.stats().hits;
  {
    const PatchCache::Pin found = cache.find(model, FakeStore::id(0));
    ASSERT_TRUE(found);
    EXPECT_EQ(versionOf(found), 1u);
    EXPECT_EQ(cache.stats().hits, hitsBefore + 1);
    EXPECT_EQ(cache.stats().pinnedBytes, kMiB);
    // Pinned by find(): loading two more into a two-patch budget evicts the other one only.
    cache.get(model, FakeStore::id(1));
    cache.get(model, FakeStore::id(2));
    EXPECT_TRUE(cache.resident(model, FakeStore::id(0)));
    EXPECT_FALSE(cache.resident(model, FakeStore::id(1)));
    EXPECT_LE(cache.stats().residentBytes, 2 * kMiB);
  }
  EXPECT_EQ(cache.stats().pinnedBytes, 0u);
  EXPECT_EQ(store.loads(), 3);
  EXPECT_EQ(cache.stats().misses, 4u);
  cache.removeModel(model);
}

TEST(PatchCache, FindCountsAsAUseSoTheClockKeepsWhatIsFound) {
  FakeStore store(8, kMiB);
  PatchCache cache(3 * kMiB, EvictionPolicy::CostAwareClock);
  const auto model = cache.addModel("m", store);
  for (int i = 0; i < 3; ++i) {
    cache.get(model, FakeStore::id(i));
  }
  // 0 and 2 are found again (referenced); 1 is not: it is the one the next load evicts.
  cache.find(model, FakeStore::id(0));
  cache.find(model, FakeStore::id(2));
  cache.get(model, FakeStore::id(3));
  EXPECT_TRUE(cache.resident(model, FakeStore::id(0)));
  EXPECT_FALSE(cache.resident(model, FakeStore::id(1)));
  EXPECT_TRUE(cache.resident(model, FakeStore::id(2)));
  cache.removeModel(model);
}

TEST(PatchCache, TheHandleBudgetClosesUnpinnedFilesOnlyAndRefusesWhenAllAreInUse) {
  FakeStore store(8, kMiB);
  PatchCache cache(64 * kMiB);
  cache.setHandleBudget(2);
  const auto model = cache.addModel("m", store);
  const auto file = [](int i) {
    return ObjectId{FakeStore::key(i), 1, MemoryCategory::OpenFiles, 1};
  };
  const auto value = [] { return CacheValue{makeBlob(64, 1), 64, 1}; };
  cache.get(model, FakeStore::id(0));  // patch data: holds no descriptor, never a victim here
  PatchCache::Pin held = cache.put(model, file(0), value(), false);
  cache.put(model, file(1), value(), false);  // unpinned at once
  EXPECT_EQ(cache.stats().handles, 2u);
  // A third file: the unpinned one goes, not the held one nor the patch data.
  PatchCache::Pin third = cache.put(model, file(2), value(), false);
  EXPECT_EQ(cache.stats().handles, 2u);
  EXPECT_TRUE(cache.resident(model, file(0)));
  EXPECT_FALSE(cache.resident(model, file(1)));
  EXPECT_TRUE(cache.resident(model, FakeStore::id(0)));
  // Both files in use: a fourth is refused, and nothing else is evicted for it.
  try {
    cache.put(model, file(3), value(), false);
    ADD_FAILURE() << "no ResourceExhausted";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::ResourceExhausted);
  }
  EXPECT_TRUE(cache.resident(model, FakeStore::id(0)));
  EXPECT_EQ(cache.stats().exhausted, 1u);
  const CacheStats stats = cache.stats();
  EXPECT_EQ(stats.handleBudget, 2u);
  EXPECT_EQ(stats.residentByCategory[static_cast<std::size_t>(MemoryCategory::OpenFiles)], 128u);
  held = {};
  third = {};
  cache.removeModel(model);
  EXPECT_EQ(cache.stats().handles, 0u);
}

TEST(PatchCache, APinHandsTheObjectOutOnlyAsTheTypeItWasPutAs) {
  FakeStore store(0, 64);
  PatchCache cache(kMiB);
  const auto model = cache.addModel("m", store);
  const ObjectId id{FakeStore::key(0), 1, MemoryCategory::Encoded, 3};
  const std::shared_ptr<const Blob> blob = makeBlob(64, 7);
  const PatchCache::Pin pin = cache.put(model, id, CacheValue{blob, 64, 0}, false);
  EXPECT_EQ(pin.get<Blob>(), blob);
  try {
    (void)pin.get<std::string>();
    ADD_FAILURE() << "a Blob was handed out as a string";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::Internal);
  }
  EXPECT_EQ(PatchCache::Pin().get<Blob>(), nullptr);
}

TEST(PatchCache, StatisticsCountByModelAndCategory) {
  FakeStore a(2, kMiB);
  FakeStore b(2, kMiB);
  PatchCache cache(8 * kMiB);
  const auto ma = cache.addModel("a", a);
  const auto mb = cache.addModel("b", b);
  cache.get(ma, FakeStore::id(0));
  cache.get(ma, FakeStore::id(0));
  cache.get(mb, FakeStore::id(1, MemoryCategory::Textures));
  const CacheStats stats = cache.stats();
  EXPECT_EQ(stats.hits, 1u);
  EXPECT_EQ(stats.misses, 2u);
  EXPECT_EQ(stats.residentByModel.at("a"), kMiB);
  EXPECT_EQ(stats.residentByModel.at("b"), kMiB);
  EXPECT_EQ(stats.residentByCategory[static_cast<int>(MemoryCategory::Positions)], kMiB);
  EXPECT_EQ(stats.residentByCategory[static_cast<int>(MemoryCategory::Textures)], kMiB);
  cache.removeModel(ma);
  cache.removeModel(mb);
}

// Issue 31: the models' metadata shares the one budget. A charge makes room as a load does
// (evicting what is not pinned, writing dirty data back first), is never refused itself, and a
// load that cannot fit beside it says that the metadata takes the room.
TEST(PatchCache, MetadataIsChargedToTheBudgetEvictsWhatItCanAndLeavesAClearRefusal) {
  FakeStore store(8, kMiB);
  PatchCache cache(4 * kMiB);
  const auto model = cache.addModel("m", store);
  const auto metadataOf = [&] {
    return cache.stats().residentByCategory[static_cast<int>(MemoryCategory::Metadata)];
  };
  for (int i = 0; i < 4; ++i) {
    cache.get(model, FakeStore::id(i));
  }
  cache.put(model, FakeStore::id(4), {makeBlob(kMiB, 9), kMiB}, true);  // dirty, unpinned
  cache.chargeMetadata(model, kMiB + kMiB / 2);
  const CacheStats stats = cache.stats();
  EXPECT_EQ(metadataOf(), kMiB + kMiB / 2);
  EXPECT_EQ(stats.residentBytes, 2 * kMiB + kMiB + kMiB / 2) << "two patches made room";
  EXPECT_EQ(stats.residentByModel.at("m"), stats.residentBytes);
  // A new charge replaces the last; a pinned patch stays even when the metadata leaves it no room.
  auto held = cache.get(model, FakeStore::id(5));
  cache.chargeMetadata(model, 4 * kMiB);
  EXPECT_TRUE(cache.resident(model, FakeStore::id(5)));
  EXPECT_EQ(cache.stats().residentBytes, 5 * kMiB) << "above the budget while pinned";
  EXPECT_EQ(store.stored(FakeStore::key(4)), 9u) << "the dirty entry was written back as it went";
  held = PatchCache::Pin();
  try {
    cache.get(model, FakeStore::id(6));
    FAIL() << "no exception";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::ResourceExhausted);
    EXPECT_NE(std::string(e.what()).find("metadata"), std::string::npos) << e.what();
  }
  EXPECT_LE(cache.stats().residentBytes, 4 * kMiB) << "the unpinned patch made room, in vain";
  cache.chargeMetadata(model, kMiB);
  EXPECT_NO_THROW(cache.get(model, FakeStore::id(6)));
  cache.removeModel(model);
  EXPECT_EQ(metadataOf(), 0u);
  EXPECT_EQ(cache.stats().residentBytes, 0u);
  EXPECT_THROW(cache.chargeMetadata(model, 1), Error) << "a removed model";
}

TEST(PatchCache, ClockKeepsAHotSetThatFifoEvicts) {
  // A hot patch used between every cold load: CLOCK keeps it (its bit is set each time), FIFO
  // throws it out once it reaches the head of the queue.
  auto run = [](EvictionPolicy policy) {
    FakeStore store(64, kMiB);
    PatchCache cache(4 * kMiB, policy);
    const auto model = cache.addModel("m", store);
    for (int i = 1; i < 64; ++i) {
      cache.get(model, FakeStore::id(0));
      cache.get(model, FakeStore::id(i));
    }
    const auto hits = cache.stats().hits;
    cache.removeModel(model);
    return hits;
  };
  EXPECT_EQ(run(EvictionPolicy::CostAwareClock), 62u);
  EXPECT_LT(run(EvictionPolicy::FifoSecondChance), 62u);
}

TEST_P(CachePolicies, ConcurrentReadersAndWritersStayWithinTheBudget) {
  constexpr int kThreads = 6;
  constexpr int kPatches = 40;
  FakeStore store(kPatches, 256 * 1024);
  PatchCache cache(2 * kMiB, GetParam());
  const auto model = cache.addModel("m", store);
  std::atomic<bool> overBudget{false};
  std::atomic<int> exhausted{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([&, t] {
      std::mt19937 rng(t);
      std::uniform_int_distribution<int> patch(0, kPatches - 1);
      for (int op = 0; op < 400; ++op) {
        const PatchKey key = FakeStore::key(patch(rng));
        try {
          if (op % 5 == 0) {
            cache.put(model, {key, 1, MemoryCategory::Positions},
                      {makeBlob(256 * 1024, 1000 + op), 256 * 1024}, true);
          } else {
            const auto pin = cache.get(model, {key, 1, MemoryCategory::Positions});
            if (pin.get<Blob>()->size() != 256 * 1024 / 8) {
              overBudget = true;
            }
          }
        } catch (const Error& e) {
          if (e.code() != ErrorCode::ResourceExhausted) {
            throw;
          }
          ++exhausted;
        }
        if (cache.stats().residentBytes > 2 * kMiB) {
          overBudget = true;
        }
      }
    });
  }
  for (auto& thread : threads) {
    thread.join();
  }
  EXPECT_FALSE(overBudget.load());
  EXPECT_FALSE(store.overlapped()) << "a key was loaded or written twice at the same time";
  // 6 threads pin at most one 256 KiB patch each: 8 fit, so nobody is ever refused.
  EXPECT_EQ(exhausted.load(), 0);
  cache.removeModel(model);
  EXPECT_EQ(cache.stats().residentBytes, 0u);
}

}  // namespace
}  // namespace vsm::core
