#include "core/cache/patch_cache.hpp"

#include <algorithm>
#include <condition_variable>
#include <limits>
#include <list>
#include <mutex>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "core/common/error.hpp"

namespace vsm::core {

std::string_view toString(MemoryCategory category) {
  switch (category) {
    case MemoryCategory::Positions:
      return "positions";
    case MemoryCategory::Coordinates:
      return "coordinates";
    case MemoryCategory::Textures:
      return "textures";
    case MemoryCategory::Encoded:
      return "encoded";
    case MemoryCategory::OpenFiles:
      return "open_files";
    case MemoryCategory::Metadata:
      return "metadata";
  }
  return "unknown";
}

std::string_view toString(EvictionPolicy policy) {
  switch (policy) {
    case EvictionPolicy::FifoSecondChance:
      return "fifo-second-chance";
    case EvictionPolicy::CostAwareClock:
      return "cost-aware-clock";
  }
  return "unknown";
}

namespace {

struct FullKey {
  PatchCache::ModelId model;
  ObjectId object;
  friend bool operator==(const FullKey&, const FullKey&) = default;
};

struct FullKeyHash {
  std::size_t operator()(const FullKey& k) const noexcept {
    return PatchKeyHash{}(k.object.key) * 131 + k.object.version * 1000003 + k.model * 7 +
           static_cast<std::size_t>(k.object.category) + (std::size_t{k.object.format} << 3);
  }
};

enum class State { Loading, Resident, WritingBack };

struct Entry {
  FullKey id;
  CachedObject object;
  /// Bytes charged to the budget: the object's size, or the reservation while loading.
  std::size_t bytes = 0;
  /// Descriptors the object holds (charged to the handle budget).
  std::size_t handles = 0;
  int pins = 0;
  bool dirty = false;
  State state = State::Loading;
  /// CLOCK: used since the hand last passed.
  bool referenced = false;
  /// FIFO: this dirty entry's second chance was spent.
  bool secondChanceSpent = false;
  /// Passes a dirty entry has survived without use (CostAwareClock).
  int dirtyPasses = 0;
  /// Invalidated while pinned: out of the table, freed when the last pin goes.
  bool detached = false;
  std::list<Entry*>::iterator ringPos;
};

struct ModelSlot {
  std::string name;
  PatchStore* store = nullptr;
  /// Its entries' bytes and its metadata charge.
  std::size_t residentBytes = 0;
  std::size_t metadataBytes = 0;
  /// Its dirty entries in the table (Impl::setDirty): a flush visits these, not the whole ring
  /// (a publish's flushers passed every entry of a full cache, 10^5 and more, for a few dozen).
  std::unordered_set<Entry*> dirty;
};

}  // namespace

struct PatchCache::Impl {
  // mutex guards everything below. It is never held across a PatchStore call.
  mutable std::mutex mutex;
  std::condition_variable changed;  // an entry left Loading/WritingBack, or an entry was removed
  std::unordered_map<FullKey, std::unique_ptr<Entry>, FullKeyHash> entries;
  /// Invalidated entries still pinned by someone.
  std::unordered_map<Entry*, std::unique_ptr<Entry>> detached;
  /// Eviction order: insertion order (FIFO) or the clock's circle (hand = clockHand).
  std::list<Entry*> ring;
  std::list<Entry*>::iterator clockHand = ring.end();
  std::unordered_map<ModelId, ModelSlot> models;
  ModelId nextModel = 1;
  std::size_t used = 0;
  std::size_t peak = 0;
  std::size_t usedHandles = 0;
  std::size_t handleBudget = std::numeric_limits<std::size_t>::max();
  std::array<std::size_t, kMemoryCategoryCount> usedByCategory{};
  std::array<std::size_t, 256> encodedByFormat{};
  std::uint64_t hits = 0, misses = 0, evictions = 0, writeBacks = 0, exhausted = 0;

  void chargeHandles(Entry& e, std::size_t handles) {
    usedHandles = usedHandles - e.handles + handles;
    e.handles = handles;
  }

  void chargeMetadata(ModelId model, std::size_t bytes) {
    ModelSlot& held = models.at(model);
    used = used - held.metadataBytes + bytes;
    peak = std::max(peak, used);
    usedByCategory[static_cast<std::size_t>(MemoryCategory::Metadata)] +=
        bytes - held.metadataBytes;
    held.residentBytes = held.residentBytes - held.metadataBytes + bytes;
    held.metadataBytes = bytes;
  }

  void charge(Entry& e, std::ptrdiff_t delta) {
    used += delta;
    peak = std::max(peak, used);
    usedByCategory[static_cast<std::size_t>(e.id.object.category)] += delta;
    if (e.id.object.category == MemoryCategory::Encoded) {
      encodedByFormat[e.id.object.format] += delta;
    }
    models.at(e.id.model).residentBytes += delta;
  }

  /// FIFO appends; CLOCK inserts just behind the hand, so a new entry is the last one it reaches.
  /// (FIFO never moves the hand, which stays at end().)
  void addToRing(Entry& e) { e.ringPos = ring.insert(clockHand, &e); }

  /// The one way an entry's dirty flag changes: kept in its model's set of dirty entries while it
  /// is in the table.
  void setDirty(Entry& e, bool dirty) {
    e.dirty = dirty;
    if (dirty && !e.detached) {
      models.at(e.id.model).dirty.insert(&e);
    } else {
      models.at(e.id.model).dirty.erase(&e);
    }
  }

  void remove(Entry& e) {
    models.at(e.id.model).dirty.erase(&e);
    charge(e, -static_cast<std::ptrdiff_t>(e.bytes));
    chargeHandles(e, 0);
    if (clockHand == e.ringPos) {
      ++clockHand;
    }
    ring.erase(e.ringPos);
    if (e.detached) {
      detached.erase(&e);  // destroys e
    } else {
      entries.erase(e.id);  // destroys e
    }
    changed.notify_all();
  }

  /// Takes a pinned entry out of the table; it stays in the ring (charged, never a victim while
  /// pinned) until its last pin goes.
  void detach(Entry& e) {
    const auto it = entries.find(e.id);
    e.detached = true;
    models.at(e.id.model).dirty.erase(&e);  // its value is discarded, never written back
    detached.emplace(&e, std::move(it->second));
    entries.erase(it);
  }

  bool evictable(const Entry& e) const { return e.pins == 0 && e.state == State::Resident; }

  /// Picks the next victim by `policy` (among entries holding descriptors only, when
  /// `forHandles`); nullptr when every such entry is pinned or in transit.
  Entry* chooseVictim(EvictionPolicy policy, bool forHandles) {
    const auto candidate = [&](const Entry& e) {
      return evictable(e) && (!forHandles || e.handles > 0);
    };
    if (ring.empty()) {
      return nullptr;
    }
    // Each entry is passed at most three times: its reference bit, a dirty entry's extra pass,
    // and the pass that takes it.
    const std::size_t maxSteps = ring.size() * 3 + 1;
    if (policy == EvictionPolicy::FifoSecondChance) {
      for (std::size_t step = 0; step < maxSteps && !ring.empty(); ++step) {
        auto it = ring.begin();
        bool moved = false;
        for (; it != ring.end(); ++it) {
          Entry& e = **it;
          if (!candidate(e)) {
            continue;
          }
          if (e.dirty && !e.secondChanceSpent) {
            e.secondChanceSpent = true;
            ring.splice(ring.end(), ring, it);
            moved = true;
            break;
          }
          return &e;
        }
        if (!moved) {
          return nullptr;
        }
      }
      return nullptr;
    }
    for (std::size_t step = 0; step < maxSteps; ++step) {
      if (clockHand == ring.end()) {
        clockHand = ring.begin();
      }
      Entry& e = **clockHand;
      ++clockHand;
      if (!candidate(e)) {
        continue;
      }
      if (e.referenced) {
        e.referenced = false;
        continue;
      }
      if (e.dirty && e.dirtyPasses == 0) {
        e.dirtyPasses = 1;
        continue;
      }
      return &e;
    }
    return nullptr;
  }

  /// True when an eviction's write-back is under way: its entry is freed when it completes.
  bool anyEvictionInTransit() const {
    for (const Entry* e : ring) {
      if (e->state == State::WritingBack && e->pins == 0) {
        return true;
      }
    }
    return false;
  }

  ModelSlot& slot(ModelId model) {
    const auto it = models.find(model);
    if (it == models.end()) {
      throw Error(ErrorCode::NotFound, "model " + std::to_string(model) + " is not in the cache");
    }
    return it->second;
  }

  /// The entry for `id` once no load or write-back is under way on it (waits on `changed` with
  /// `lock`); nullptr when there is none.
  Entry* settled(std::unique_lock<std::mutex>& lock, const FullKey& id) {
    for (;;) {
      const auto it = entries.find(id);
      if (it == entries.end()) {
        return nullptr;
      }
      if (it->second->state == State::Resident) {
        return it->second.get();
      }
      changed.wait(lock);
    }
  }

  void makeRoom(std::unique_lock<std::mutex>& lock, std::size_t needed, std::size_t budget,
                EvictionPolicy policy, std::size_t neededHandles = 0);
  /// makeRoom's evictions: false, having evicted what it could, when what is left is pinned.
  bool evictUntilFits(std::unique_lock<std::mutex>& lock, std::size_t needed, std::size_t budget,
                      EvictionPolicy policy, std::size_t neededHandles);

  /// The one write-back protocol (an eviction's and a flush's): writes dirty `e` through its
  /// model's store with `lock` released, `e` WritingBack meanwhile (resident and readable, but
  /// not chosen, flushed or dropped by anyone else). `pin`: holds a pin while unlocked (a flush
  /// keeps its target alive; an eviction's victim stays unpinned, which anyEvictionInTransit()
  /// counts on). Returns with `lock` held and `e` Resident again, clean unless a put() replaced
  /// its object meanwhile (then it stays dirty with the new object). On the store's error
  /// restores the state and rethrows. Either way wakes those waiting on `changed`.
  void writeBackUnlocked(std::unique_lock<std::mutex>& lock, Entry& e, bool pin);
};

PatchCache::PatchCache(std::size_t budgetBytes, EvictionPolicy policy)
    : budget_(budgetBytes), policy_(policy), impl_(std::make_unique<Impl>()) {}

PatchCache::~PatchCache() = default;

// ---- Pin -------------------------------------------------------------------------------------

PatchCache::Pin::Pin(Pin&& other) noexcept
    : cache_(other.cache_), entry_(other.entry_), object_(std::move(other.object_)) {
  other.cache_ = nullptr;
  other.entry_ = nullptr;
}

PatchCache::Pin& PatchCache::Pin::operator=(Pin&& other) noexcept {
  if (this != &other) {
    release();
    cache_ = other.cache_;
    entry_ = other.entry_;
    object_ = std::move(other.object_);
    other.cache_ = nullptr;
    other.entry_ = nullptr;
  }
  return *this;
}

PatchCache::Pin::~Pin() {
  release();
}

void CachedObject::throwTypeMismatch(const std::type_info& wanted) const {
  throw Error(ErrorCode::Internal, std::string("cache: an object of type ") + type_->name() +
                                       " was asked for as " + wanted.name());
}

void PatchCache::Pin::release() {
  if (cache_ != nullptr && entry_ != nullptr) {
    cache_->unpin(entry_);
  }
  cache_ = nullptr;
  entry_ = nullptr;
  object_ = {};
}

std::size_t PatchCache::Pin::bytes() const {
  if (cache_ == nullptr) {
    return 0;
  }
  std::lock_guard lock(cache_->impl_->mutex);
  return static_cast<const Entry*>(entry_)->bytes;
}

void PatchCache::unpin(void* entry) {
  std::lock_guard lock(impl_->mutex);
  Entry& e = *static_cast<Entry*>(entry);
  if (--e.pins == 0 && e.detached) {
    impl_->remove(e);
  }
}

// ---- models ----------------------------------------------------------------------------------

PatchCache::ModelId PatchCache::addModel(std::string name, PatchStore& store) {
  std::lock_guard lock(impl_->mutex);
  const ModelId id = impl_->nextModel++;
  ModelSlot slot;
  slot.name = std::move(name);
  slot.store = &store;
  impl_->models.emplace(id, std::move(slot));
  return id;
}

void PatchCache::removeModel(ModelId model) {
  flush(model);  // throws NotFound for an unknown model
  std::unique_lock lock(impl_->mutex);
  for (;;) {
    // One pass, as flushEntries: the model's entries, none pinned, removed under the lock.
    std::vector<Entry*> victims;
    bool waiting = false;
    for (Entry* e : impl_->ring) {
      if (e->id.model != model) {
        continue;
      }
      if (e->state != State::Resident) {
        waiting = true;
        continue;
      }
      if (e->pins > 0) {
        throw Error(ErrorCode::Conflict, "model is still in use");
      }
      victims.push_back(e);
    }
    for (Entry* e : victims) {
      impl_->remove(*e);
    }
    if (waiting) {
      impl_->changed.wait(lock);
    } else {
      break;
    }
  }
  impl_->chargeMetadata(model, 0);
  impl_->models.erase(model);
}

void PatchCache::chargeMetadata(ModelId model, std::size_t bytes) {
  std::unique_lock lock(impl_->mutex);
  impl_->slot(model);  // NotFound for an unknown model
  impl_->chargeMetadata(model, bytes);
  impl_->evictUntilFits(lock, 0, budget_, policy_, 0);  // what stays pinned stays
}

// ---- room ------------------------------------------------------------------------------------

/// Makes room for `needed` more bytes and `neededHandles` more descriptors. Called and returns
/// with `lock` held; releases it while a dirty victim is written back. Throws
/// Error(ResourceExhausted) when everything left is pinned.
void PatchCache::Impl::makeRoom(std::unique_lock<std::mutex>& lock, std::size_t needed,
                                std::size_t budget, EvictionPolicy policy,
                                std::size_t neededHandles) {
  if (needed > budget || neededHandles > handleBudget) {
    ++exhausted;
    throw Error(ErrorCode::ResourceExhausted,
                needed > budget
                    ? "object of " + std::to_string(needed) +
                          " bytes exceeds the memory budget of " + std::to_string(budget) + " bytes"
                    : "object holds more descriptors than the cache may");
  }
  if (!evictUntilFits(lock, needed, budget, policy, neededHandles)) {
    ++exhausted;
    const std::size_t metadata = usedByCategory[static_cast<std::size_t>(MemoryCategory::Metadata)];
    std::string why;
    if (used + needed <= budget) {
      why = "every one of the " + std::to_string(handleBudget) +
            " open files the cache may hold is in use";
    } else if (metadata + needed > budget) {
      why = "object of " + std::to_string(needed) + " bytes does not fit in the memory budget of " +
            std::to_string(budget) + " bytes beside the " + std::to_string(metadata) +
            " bytes of the open models' metadata: raise the budget";
    } else {
      why = "memory budget of " + std::to_string(budget) +
            " bytes is exhausted: every resident patch is in use";
    }
    throw Error(ErrorCode::ResourceExhausted, why);
  }
}

bool PatchCache::Impl::evictUntilFits(std::unique_lock<std::mutex>& lock, std::size_t needed,
                                      std::size_t budget, EvictionPolicy policy,
                                      std::size_t neededHandles) {
  Impl& impl = *this;
  for (;;) {
    const bool bytesShort = impl.used + needed > budget;
    const bool handlesShort = impl.usedHandles + neededHandles > impl.handleBudget;
    if (!bytesShort && !handlesShort) {
      return true;
    }
    Entry* victim = impl.chooseVictim(policy, !bytesShort);
    if (victim == nullptr) {
      if (impl.anyEvictionInTransit()) {
        impl.changed.wait(lock);
        continue;
      }
      return false;
    }
    if (!victim->dirty) {
      ++impl.evictions;
      impl.remove(*victim);
      continue;
    }
    impl.writeBackUnlocked(lock, *victim, /*pin=*/false);
    if (impl.evictable(*victim) && !victim->dirty) {
      ++impl.evictions;
      impl.remove(*victim);
    }
  }
}

void PatchCache::Impl::writeBackUnlocked(std::unique_lock<std::mutex>& lock, Entry& e, bool pin) {
  e.state = State::WritingBack;
  if (pin) {
    ++e.pins;  // keeps the entry alive while unlocked
  }
  const FullKey id = e.id;
  const CacheValue value{e.object, e.bytes};
  PatchStore* store = slot(id.model).store;
  lock.unlock();
  try {
    store->writeBack(id.object, value);
  } catch (...) {
    lock.lock();
    e.state = State::Resident;
    if (pin) {
      --e.pins;
    }
    changed.notify_all();
    throw;
  }
  lock.lock();
  ++writeBacks;
  e.state = State::Resident;
  if (pin) {
    --e.pins;
  }
  // A put() during the write-back replaces object and sets dirty again: keep it then.
  if (e.object == value.object) {
    setDirty(e, false);
    e.dirtyPasses = 0;
  }
  changed.notify_all();
}

// ---- access ----------------------------------------------------------------------------------

PatchCache::Pin PatchCache::get(ModelId model, const ObjectId& object) {
  const FullKey id{model, object};
  std::unique_lock lock(impl_->mutex);
  PatchStore* store = impl_->slot(model).store;
  for (;;) {
    const auto it = impl_->entries.find(id);
    if (it == impl_->entries.end()) {
      break;
    }
    Entry& e = *it->second;
    if (e.state == State::Loading) {
      impl_->changed.wait(lock);
      continue;
    }
    ++impl_->hits;
    ++e.pins;
    e.referenced = true;
    e.dirtyPasses = 0;
    return Pin(this, &e, e.object);
  }

  ++impl_->misses;
  lock.unlock();
  const std::size_t expected = store->expectedBytes(object);
  lock.lock();
  impl_->makeRoom(lock, expected, budget_, policy_);
  // Another thread may have started loading the same key while the lock was released.
  if (impl_->entries.count(id) != 0) {
    --impl_->misses;
    lock.unlock();
    return get(model, object);
  }
  auto owned = std::make_unique<Entry>();
  Entry& e = *owned;
  e.id = id;
  e.bytes = expected;
  e.pins = 1;
  impl_->entries.emplace(id, std::move(owned));
  impl_->addToRing(e);
  impl_->charge(e, static_cast<std::ptrdiff_t>(expected));

  lock.unlock();
  CacheValue value;
  try {
    value = store->load(object);
  } catch (...) {
    lock.lock();
    impl_->remove(e);
    throw;
  }
  lock.lock();
  if (value.bytes > e.bytes) {
    const std::size_t extra = value.bytes - e.bytes;
    try {  // still Loading and pinned: neither a victim nor served while we make room
      impl_->makeRoom(lock, extra, budget_, policy_);
    } catch (...) {
      impl_->remove(e);
      throw;
    }
  }
  impl_->charge(e, static_cast<std::ptrdiff_t>(value.bytes) - static_cast<std::ptrdiff_t>(e.bytes));
  e.bytes = value.bytes;
  e.object = std::move(value.object);
  e.state = State::Resident;
  impl_->changed.notify_all();
  return Pin(this, &e, e.object);
}

void PatchCache::countMiss() {
  const std::lock_guard lock(impl_->mutex);
  ++impl_->misses;
}

PatchCache::Pin PatchCache::find(ModelId model, const ObjectId& object, bool countMiss) {
  const std::lock_guard lock(impl_->mutex);
  const auto it = impl_->entries.find(FullKey{model, object});
  if (it == impl_->entries.end() || it->second->state == State::Loading) {
    if (countMiss) {
      ++impl_->misses;
    }
    return {};
  }
  Entry& e = *it->second;
  ++impl_->hits;
  ++e.pins;
  e.referenced = true;
  e.dirtyPasses = 0;
  return Pin(this, &e, e.object);
}

PatchCache::Pin PatchCache::put(ModelId model, const ObjectId& object, CacheValue value,
                                bool dirty) {
  const FullKey id{model, object};
  std::unique_lock lock(impl_->mutex);
  impl_->slot(model);
  if (Entry* settled = impl_->settled(lock, id); settled != nullptr) {
    Entry& e = *settled;
    // Replace in place: pin first so making room cannot evict it.
    ++e.pins;
    if (value.bytes > e.bytes || value.handles > e.handles) {
      try {
        impl_->makeRoom(lock, value.bytes > e.bytes ? value.bytes - e.bytes : 0, budget_, policy_,
                        value.handles > e.handles ? value.handles - e.handles : 0);
      } catch (...) {
        --e.pins;
        throw;
      }
    }
    impl_->charge(e,
                  static_cast<std::ptrdiff_t>(value.bytes) - static_cast<std::ptrdiff_t>(e.bytes));
    impl_->chargeHandles(e, value.handles);
    e.bytes = value.bytes;
    e.object = std::move(value.object);
    if (dirty && !e.dirty) {
      e.secondChanceSpent = false;
    }
    if (dirty) {
      impl_->setDirty(e, true);
    }
    e.referenced = true;
    e.dirtyPasses = 0;
    return Pin(this, &e, e.object);
  }
  impl_->makeRoom(lock, value.bytes, budget_, policy_, value.handles);
  if (impl_->entries.count(id) != 0) {
    lock.unlock();
    return put(model, object, std::move(value), dirty);
  }
  auto owned = std::make_unique<Entry>();
  Entry& e = *owned;
  e.id = id;
  e.bytes = value.bytes;
  e.object = std::move(value.object);
  e.pins = 1;
  e.state = State::Resident;
  e.referenced = true;
  impl_->entries.emplace(id, std::move(owned));
  impl_->setDirty(e, dirty);
  impl_->addToRing(e);
  impl_->charge(e, static_cast<std::ptrdiff_t>(e.bytes));
  impl_->chargeHandles(e, value.handles);
  return Pin(this, &e, e.object);
}

void PatchCache::flush(ModelId model) {
  flushEntries(model, nullptr);
}

void PatchCache::flush(ModelId model, const ObjectId& object) {
  flushEntries(model, &object);
}

void PatchCache::flushEntries(ModelId model, const ObjectId* only) {
  std::unique_lock lock(impl_->mutex);
  impl_->slot(model);  // throws NotFound for a model not in the cache
  // One object: looked up, not searched for (an edit flushes each patch it writes: a pass over
  // the ring each took 1.7 s of a merge job at 10^6 patches, the cache holding 10^5 entries).
  while (only != nullptr) {
    const auto it = impl_->entries.find(FullKey{model, *only});
    if (it == impl_->entries.end() || !it->second->dirty) {
      return;
    }
    if (it->second->state != State::Resident) {
      impl_->changed.wait(lock);
    } else {
      impl_->writeBackUnlocked(lock, *it->second, /*pin=*/true);
    }
  }
  for (;;) {
    // The model's dirty entries collected, then each written back (the lock released meanwhile,
    // so each is looked up again).
    std::vector<FullKey> dirty;
    bool waiting = false;
    for (const Entry* e : impl_->models.at(model).dirty) {
      if (e->state != State::Resident) {
        waiting = true;
      } else {
        dirty.push_back(e->id);
      }
    }
    if (dirty.empty()) {
      if (!waiting) {
        return;
      }
      impl_->changed.wait(lock);
      continue;
    }
    for (const FullKey& id : dirty) {
      const auto it = impl_->entries.find(id);
      if (it != impl_->entries.end() && it->second->dirty && it->second->state == State::Resident) {
        impl_->writeBackUnlocked(lock, *it->second, /*pin=*/true);
      }
    }
  }
}

void PatchCache::drop(ModelId model, const ObjectId& object) {
  std::unique_lock lock(impl_->mutex);
  Entry* e = impl_->settled(lock, FullKey{model, object});
  if (e == nullptr) {
    return;
  }
  if (e->pins > 0) {
    throw Error(ErrorCode::Conflict, "patch " + object.key.toString() + " is in use");
  }
  impl_->remove(*e);
}

void PatchCache::invalidate(ModelId model, const ObjectId& object) {
  std::unique_lock lock(impl_->mutex);
  Entry* e = impl_->settled(lock, FullKey{model, object});
  if (e == nullptr) {
    return;
  }
  if (e->pins > 0) {
    impl_->detach(*e);
  } else {
    impl_->remove(*e);
  }
}

void PatchCache::setHandleBudget(std::size_t handles) {
  const std::lock_guard lock(impl_->mutex);
  impl_->handleBudget = handles;
}

bool PatchCache::resident(ModelId model, const ObjectId& object) const {
  std::lock_guard lock(impl_->mutex);
  const auto it = impl_->entries.find(FullKey{model, object});
  return it != impl_->entries.end() && it->second->state != State::Loading;
}

CacheStats PatchCache::stats() const {
  std::lock_guard lock(impl_->mutex);
  CacheStats s;
  s.budgetBytes = budget_;
  s.residentBytes = impl_->used;
  s.peakResidentBytes = impl_->peak;
  s.residentByCategory = impl_->usedByCategory;
  for (std::size_t format = 0; format < impl_->encodedByFormat.size(); ++format) {
    if (impl_->encodedByFormat[format] != 0) {
      s.encodedByFormat[static_cast<std::uint8_t>(format)] = impl_->encodedByFormat[format];
    }
  }
  for (const auto& [id, slot] : impl_->models) {
    s.residentByModel[slot.name] += slot.residentBytes;
  }
  for (const Entry* e : impl_->ring) {
    if (e->pins > 0) {
      s.pinnedBytes += e->bytes;
    }
  }
  s.handles = impl_->usedHandles;
  s.handleBudget = impl_->handleBudget;
  s.hits = impl_->hits;
  s.misses = impl_->misses;
  s.evictions = impl_->evictions;
  s.writeBacks = impl_->writeBacks;
  s.exhausted = impl_->exhausted;
  return s;
}

}  // namespace vsm::core
