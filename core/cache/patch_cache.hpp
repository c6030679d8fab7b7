#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <map>
#include <memory>
#include <string>
#include <typeinfo>

#include "core/pyramid/patch_key.hpp"

namespace vsm::core {

/// What a cached object is, for accounting against the budget by category: patch data as the
/// store loads it (Positions, Coordinates, Textures); Encoded, data the cache's user derived from
/// patch data (a file format, a compressed image), its kind told by ObjectId::format; OpenFiles,
/// stored files the user holds open (their bookkeeping bytes; each holds descriptors, counted
/// against the handle budget); Metadata, what the open models hold in memory besides (their trees
/// of patch descriptions: PatchCache::chargeMetadata), never an entry.
enum class MemoryCategory : std::uint8_t {
  Positions = 0,
  Coordinates,
  Textures,
  Encoded,
  OpenFiles,
  Metadata
};
inline constexpr std::size_t kMemoryCategoryCount = 6;
std::string_view toString(MemoryCategory category);

/// What the cache holds: one version of one kind of data of one patch. Versions of a key are
/// distinct entries, so a reader of an older published version and a writer preparing the next
/// one never see each other's data.
struct ObjectId {
  PatchKey key;
  std::uint64_t version = 1;
  MemoryCategory category = MemoryCategory::Positions;
  /// Which encoding or file, for Encoded and OpenFiles entries: chosen by the cache's user, opaque
  /// to the cache (0 for patch data).
  std::uint8_t format = 0;
  friend bool operator==(const ObjectId&, const ObjectId&) = default;
};

/// An immutable object of any type, shared, that remembers its type: as<T>() hands it out only as
/// the type it was made from (a mismatch is a bug, reported as Error(Internal)), so the cache can
/// hold grids, tiles, encodings and open files side by side without unchecked casts.
class CachedObject {
 public:
  CachedObject() = default;
  template <typename T>
  CachedObject(std::shared_ptr<T> object)  // NOLINT(google-explicit-constructor): a conversion
      : object_(std::move(object)), type_(&typeid(std::remove_const_t<T>)) {}

  /// The object as a T; null when empty. Throws Error(Internal) when it was made from another type.
  template <typename T>
  std::shared_ptr<const T> as() const {
    if (object_ == nullptr) {
      return nullptr;
    }
    if (*type_ != typeid(T)) {
      throwTypeMismatch(typeid(T));
    }
    return std::static_pointer_cast<const T>(object_);
  }
  explicit operator bool() const { return object_ != nullptr; }
  /// The same object (not merely equal contents).
  friend bool operator==(const CachedObject& a, const CachedObject& b) {
    return a.object_ == b.object_;
  }

 private:
  [[noreturn]] void throwTypeMismatch(const std::type_info& wanted) const;

  std::shared_ptr<const void> object_;
  const std::type_info* type_ = nullptr;
};

/// A loaded object, the bytes it occupies and the descriptors (open files) it holds.
struct CacheValue {
  CachedObject object;
  std::size_t bytes = 0;
  std::size_t handles = 0;
};

/// The backing store of one model: where the cache loads from and writes dirty data back to.
/// Implemented by the model's owner (e.g. over an OPC directory). Called WITHOUT any cache lock
/// held, possibly from several threads at once for different keys; never twice at once for the same
/// object.
class PatchStore {
 public:
  virtual ~PatchStore() = default;
  /// Bytes the object will occupy once loaded; used to make room before loading.
  virtual std::size_t expectedBytes(const ObjectId& id) const = 0;
  /// Loads an object. Throws Error (NotFound, Corrupt, Io) as the store does.
  virtual CacheValue load(const ObjectId& id) = 0;
  /// Writes a dirty object back, atomically. Throws Error(Io) on failure (the entry then stays
  /// resident and dirty).
  virtual void writeBack(const ObjectId& id, const CacheValue& value) = 0;
};

enum class EvictionPolicy {
  /// The thesis' baseline: first in, first out; a dirty entry at the head gets one second chance
  /// (moved to the tail) so clean entries are dropped before anything is written.
  FifoSecondChance,
  /// CLOCK with a write-back cost: an entry used since the hand last passed gets a second chance;
  /// a dirty one needs two passes without use (writing it back costs a disk write).
  CostAwareClock,
};
std::string_view toString(EvictionPolicy policy);

struct CacheStats {
  std::size_t budgetBytes = 0;
  std::size_t residentBytes = 0;
  /// The most ever resident at once.
  std::size_t peakResidentBytes = 0;
  std::size_t pinnedBytes = 0;
  /// Descriptors held by entries (CacheValue::handles), and their bound (setHandleBudget()).
  std::size_t handles = 0;
  std::size_t handleBudget = 0;
  std::array<std::size_t, kMemoryCategoryCount> residentByCategory{};
  /// Resident bytes of Encoded entries by ObjectId::format (formats with none left out).
  std::map<std::uint8_t, std::size_t> encodedByFormat;
  /// Model name -> resident bytes.
  std::map<std::string, std::size_t> residentByModel;
  std::uint64_t hits = 0;
  std::uint64_t misses = 0;
  std::uint64_t evictions = 0;
  std::uint64_t writeBacks = 0;
  /// Loads and puts refused because everything resident (or every entry holding descriptors) was
  /// pinned.
  std::uint64_t exhausted = 0;
};

/// One memory budget over every open model: the objects loaded through the cache, and the models'
/// metadata as their users charge it (chargeMetadata). Resident bytes never exceed the budget:
/// room is made *before* a load by evicting unpinned entries (clean ones dropped, dirty ones
/// written back first); when that is not enough the caller gets Error(ResourceExhausted), never an
/// allocation failure. Metadata is never evicted: a charge makes room as a load does, and when the
/// metadata alone leaves no room, loads fail so, saying so. A second,
/// smaller budget bounds the descriptors entries hold (open files put by the user), so that the
/// process never runs out of them: beyond it the least recently used unpinned file is closed.
///
/// Thread-safe. One mutex guards the table, the policy state and the counters; it is never held
/// across a PatchStore call (load or write-back) — entries being loaded or written back are marked
/// in the table and other threads wait on a condition variable for them.
class PatchCache {
 public:
  using ModelId = std::uint32_t;

  explicit PatchCache(std::size_t budgetBytes,
                      EvictionPolicy policy = EvictionPolicy::CostAwareClock);
  /// Precondition: every model removed (their dirty data written back).
  ~PatchCache();
  PatchCache(const PatchCache&) = delete;
  PatchCache& operator=(const PatchCache&) = delete;

  /// An RAII hold on a resident object: while it lives the entry is never evicted. Movable.
  class Pin {
   public:
    Pin() = default;
    Pin(Pin&& other) noexcept;
    Pin& operator=(Pin&& other) noexcept;
    ~Pin();

    explicit operator bool() const { return entry_ != nullptr; }
    /// The object as the type it was put or loaded as (Error(Internal) for another type).
    template <typename T>
    std::shared_ptr<const T> get() const {
      return object_.as<T>();
    }
    std::size_t bytes() const;

   private:
    friend class PatchCache;
    Pin(PatchCache* cache, void* entry, CachedObject object)
        : cache_(cache), entry_(entry), object_(std::move(object)) {}
    void release();

    PatchCache* cache_ = nullptr;
    void* entry_ = nullptr;
    CachedObject object_;
  };

  /// Registers a model; `store` must outlive removeModel(). `name` is for statistics.
  ModelId addModel(std::string name, PatchStore& store);
  /// Writes back the model's dirty entries and drops all of them, and its metadata charge.
  /// Precondition: none pinned. Throws the store's error when a write-back fails (entries stay
  /// until a retry succeeds).
  void removeModel(ModelId model);

  /// Sets the bytes of metadata the model holds in memory (MemoryCategory::Metadata, replacing its
  /// last charge) and evicts unpinned entries until everything fits again, as far as they allow:
  /// metadata is there whether it fits or not, so this never fails for want of room (resident
  /// bytes then stay above the budget until entries are unpinned). Throws Error(NotFound) for an
  /// unknown model, and the store's error when a dirty entry's write-back fails.
  void chargeMetadata(ModelId model, std::size_t bytes);

  /// Returns the object, loading it on a miss. Throws Error(ResourceExhausted) when it cannot fit
  /// even after evicting everything unpinned, or the store's error.
  Pin get(ModelId model, const ObjectId& id);

  /// The object, pinned, when it is resident; an empty Pin when it is not (or still loading).
  /// Never loads and never waits (the lock is held for a table look-up only): for callers that
  /// must not block (network threads). The pin keeps the entry charged and unevictable while, say,
  /// a response is written from it. Counts a hit, and a miss unless `countMiss` is false (a second
  /// look for the same request, whose first look counted it); a hit counts as a use for the
  /// eviction policy.
  Pin find(ModelId model, const ObjectId& id, bool countMiss = true);
  /// Counts one miss: for a caller that looked for one thing in several forms with find(...,
  /// false) and found none of them.
  void countMiss();

  /// Inserts or replaces an object (new data from a merge or import, an encoding, an open file),
  /// resident and pinned. When `dirty`, it is written back before it is ever evicted. Throws
  /// Error(ResourceExhausted) when its bytes or its handles do not fit beside what is pinned.
  Pin put(ModelId model, const ObjectId& id, CacheValue value, bool dirty);

  /// Writes back every dirty entry of the model (they stay resident, now clean). Safe to call
  /// from several threads at once: each writes back entries no other is writing, and each
  /// returns when all are written (or rethrows its own write-back's error).
  void flush(ModelId model);
  /// flush() of one entry: writes it back when it is dirty (waiting while another thread writes
  /// it); nothing when it is clean or not resident.
  void flush(ModelId model, const ObjectId& object);
  /// Forgets an entry without writing it back (its data is obsolete). Precondition: not pinned.
  void drop(ModelId model, const ObjectId& id);
  /// Forgets an entry whose stored data was replaced behind the cache (a published new version):
  /// the next get() loads afresh. Holders of pins keep their (old) object; its bytes stay charged
  /// until the last pin goes. Never writes back.
  void invalidate(ModelId model, const ObjectId& id);

  /// Bounds the descriptors held by entries (CacheValue::handles); default: no bound. Entries
  /// beyond a lowered bound go as room is next made. Thread-safe.
  void setHandleBudget(std::size_t handles);

  bool resident(ModelId model, const ObjectId& id) const;
  CacheStats stats() const;
  std::size_t budgetBytes() const { return budget_; }
  EvictionPolicy policy() const { return policy_; }

 private:
  struct Impl;  // the table, the policy state and the counters; defined in the .cpp
  void unpin(void* entry);
  void flushEntries(ModelId model, const ObjectId* only);  // only: null for every entry

  std::size_t budget_;
  EvictionPolicy policy_;
  std::unique_ptr<Impl> impl_;
};

}  // namespace vsm::core
