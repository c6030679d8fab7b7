#include "core/pyramid/model.hpp"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <string_view>

#include "core/common/error.hpp"
#include "core/pyramid/reduce.hpp"

namespace vsm::core {

PackedRect::PackedRect(const GridRect& rect) {
  if (!fits(rect)) {
    throw Error(ErrorCode::InvalidArgument, "a stored rectangle outside 0..65535");
  }
  x0 = static_cast<std::uint16_t>(rect.x0);
  y0 = static_cast<std::uint16_t>(rect.y0);
  x1 = static_cast<std::uint16_t>(rect.x1);
  y1 = static_cast<std::uint16_t>(rect.y1);
}

bool PackedRect::fits(const GridRect& rect) {
  constexpr int kMax = 65535;
  return std::min({rect.x0, rect.y0, rect.x1, rect.y1}) >= 0 &&
         std::max({rect.x0, rect.y0, rect.x1, rect.y1}) <= kMax;
}

const PatchFiles PatchInfo::kUntexturedFiles;

template <typename Change>
void PatchInfo::changeExtras(Change change) {
  Extras extras = extras_ ? static_cast<const Extras&>(*extras_) : Extras{};
  change(extras);
  if (extras.folder.empty() && !extras.matrix && !extras.files) {
    extras_.reset();
  } else {
    extras_.reset(new CountedExtras(std::move(extras)));
  }
}

std::string PatchInfo::folder() const {
  return ownFolder() ? extras_->folder : key.toString();
}

std::string_view PatchInfo::folder(char (&buffer)[PatchKey::kMaxText]) const {
  return ownFolder() ? std::string_view(extras_->folder) : key.toChars(buffer);
}

void PatchInfo::setFolder(std::string folder) {
  // Called for each of 1.4 million patches when an index is read at 10^6: no string built.
  char buffer[PatchKey::kMaxText];
  if (!folder.empty() && folder == key.toChars(buffer)) {
    folder.clear();
  }
  if (folder != (extras_ ? std::string_view(extras_->folder) : std::string_view())) {
    changeExtras([&folder](Extras& extras) { extras.folder = std::move(folder); });
  }
}

void PatchInfo::setLocal2Global(const Mat4d& m) {
  // Bit for bit (a -0 in a foreign OPC's linear part is kept, and written back, as it was).
  const Mat4d shift = Mat4d::translation(m.translationPart());
  if (std::memcmp(m.m.data(), shift.m.data(), sizeof m.m) == 0) {
    translation_ = m.translationPart();
    if (extras_ && extras_->matrix) {
      changeExtras([](Extras& extras) { extras.matrix.reset(); });
    }
  } else {
    translation_ = {};
    changeExtras([&m](Extras& extras) { extras.matrix = std::make_shared<const Mat4d>(m); });
  }
}

void PatchInfo::setFiles(PatchFiles files) {
  if (files == this->files()) {
    return;
  }
  changeExtras([&files](Extras& extras) {
    extras.files =
        files == kUntexturedFiles ? nullptr : std::make_shared<const PatchFiles>(std::move(files));
  });
}

namespace {

/// Heap bytes of a string's own buffer (none within the small-string buffer), with overhead.
std::size_t heapOf(const std::string& text) {
  return text.capacity() > 15 ? text.capacity() + 1 + 16 : 0;
}

/// A make_shared block of a T: the object, its control block, the allocator's overhead.
template <typename T>
constexpr std::size_t sharedBlock = sizeof(T) + 16 + 16;

}  // namespace

std::size_t PatchInfo::ownHeapBytes() const {
  if (!extras_) {
    return 0;
  }
  std::size_t bytes = sizeof(CountedExtras) + 16 + heapOf(extras_->folder) +
                      (extras_->matrix ? sharedBlock<Mat4d> : 0);
  if (const auto& files = extras_->files) {
    bytes += sharedBlock<PatchFiles> + heapOf(files->positions) + heapOf(files->coordinates) +
             heapOf(files->texture);
  }
  return bytes;
}

Model::Model(int gridSize) : gridSize_(gridSize) {
  // The range first: gridSize - 1 of any int (a size read from a damaged file) must not overflow.
  const bool inRange = gridSize >= 3 && gridSize <= (1 << 15) + 1;
  const int intervals = inRange ? gridSize - 1 : 0;
  if (!inRange || (intervals & (intervals - 1)) != 0) {
    throw Error(ErrorCode::InvalidArgument,
                "patch size " + std::to_string(gridSize) + " is not 2^n+1 with n in 1..15");
  }
}

int Model::maxDepth() const {
  // Keys order by depth first.
  return size_ == 0 ? -1 : chunks_.back()->back().key.depth;
}

Model::Place Model::locate(const PatchKey& key) const {
  // The first chunk whose last key is not before `key`, then the place in it.
  const auto chunk =
      std::partition_point(chunks_.begin(), chunks_.end(),
                           [&key](const std::shared_ptr<Chunk>& c) { return c->back().key < key; });
  if (chunk == chunks_.end()) {
    return {chunks_.size(), 0, false};
  }
  const auto entry = std::partition_point((*chunk)->begin(), (*chunk)->end(),
                                          [&key](const PatchInfo& p) { return p.key < key; });
  return {static_cast<std::size_t>(chunk - chunks_.begin()),
          static_cast<std::size_t>(entry - (*chunk)->begin()), entry->key == key};
}

/// What levels() sums of one chunk, per depth in it (keys order by depth first: one or two), and
/// what heapBytes() counts of it.
struct Model::ChunkSums {
  struct Level {
    int depth = 0;
    std::size_t patches = 0;
    std::size_t leaves = 0;
    std::size_t hidden = 0;
    std::size_t measured = 0;
    Box3d bounds;
    std::int64_t nanometres = 0;  // the measured resolutions' sum (< 2^63: 256 of <= 1e7 m each)
    double finestLeaf = 0;        // 0: no leaf with a resolution
  };
  std::vector<Level> levels;
  /// Heap bytes of the chunk and its nodes (Model::heapBytes).
  std::size_t bytes = 0;
};

Model::Chunk::~Chunk() {
  delete sums.load();
}

Model::Chunk& Model::writableChunk(std::size_t chunk) {
  // Shared: another model (or a shared() pointer) holds it too, and may be reading it elsewhere,
  // so this one takes a copy, without sums yet. Not shared: only this model can reach it, and no
  // other can start sharing it while this one is being changed (a copy of a model being changed
  // is a race already); it drops its sums.
  std::shared_ptr<Chunk>& held = chunks_[chunk];
  if (held.use_count() > 1) {
    held = std::make_shared<Chunk>(*held);
  } else {
    delete held->sums.exchange(nullptr);
  }
  return *held;
}

const PatchInfo* Model::find(const PatchKey& key) const {
  const Place place = locate(key);
  return place.found ? &(*chunks_[place.chunk])[place.index] : nullptr;
}

const PatchInfo& Model::at(const PatchKey& key) const {
  const PatchInfo* info = find(key);
  if (info == nullptr) {
    throw Error(ErrorCode::NotFound, "no patch " + key.toString());
  }
  return *info;
}

PatchInfo& Model::edit(const PatchKey& key) {
  const Place place = locate(key);
  if (!place.found) {
    throw Error(ErrorCode::NotFound, "no patch " + key.toString());
  }
  return writableChunk(place.chunk)[place.index];
}

std::shared_ptr<const PatchInfo> Model::shared(const PatchKey& key) const {
  const Place place = locate(key);
  if (!place.found) {
    throw Error(ErrorCode::NotFound, "no patch " + key.toString());
  }
  // Aliasing the chunk: it stays as it is while the pointer is held (writableChunk copies it).
  const std::shared_ptr<Chunk>& chunk = chunks_[place.chunk];
  return std::shared_ptr<const PatchInfo>(chunk, &(*chunk)[place.index]);
}

PatchInfo& Model::insert(PatchInfo info) {
  // After every key held (a model read in key order, parents first): no child of it can be here
  // yet, and it goes at the end of the last chunk, or starts a new one.
  const bool last = size_ == 0 || chunks_.back()->back().key < info.key;
  const Place place = last ? Place{chunks_.size(), 0, false} : locate(info.key);
  if (place.found) {
    throw Error(ErrorCode::Conflict, "patch " + info.key.toString() + " exists");
  }
  if (const auto parentKey = info.key.parent()) {
    const Place parent = locate(*parentKey);
    if (!parent.found) {
      throw Error(ErrorCode::InvalidArgument,
                  "patch " + info.key.toString() + " has no parent in the model");
    }
    writableChunk(parent.chunk)[parent.index].childMask |=
        static_cast<std::uint8_t>(1u << static_cast<int>(info.key.quadrant()));
  }
  info.childMask = 0;
  for (const Quadrant q : kQuadrants) {
    if (!last && find(info.key.child(q)) != nullptr) {
      info.childMask |= static_cast<std::uint8_t>(1u << static_cast<int>(q));
    }
  }
  ++size_;
  if (last) {
    if (chunks_.empty() || chunks_.back()->size() >= kChunkSize) {
      chunks_.push_back(std::make_shared<Chunk>());
      chunks_.back()->reserve(kChunkSize);
    }
    return writableChunk(chunks_.size() - 1).emplace_back(std::move(info));
  }
  // Not last, so some chunk holds a later key and locate() named it. A full chunk is split first,
  // in halves of their own size (a vector grown past kChunkSize would keep twice the room).
  std::size_t c = place.chunk;
  std::size_t index = place.index;
  if (chunks_[c]->size() >= kChunkSize) {
    const Chunk& full = *chunks_[c];
    const auto half = full.begin() + static_cast<std::ptrdiff_t>(full.size() / 2);
    auto lower = std::make_shared<Chunk>(full.begin(), half);
    auto upper = std::make_shared<Chunk>(half, full.end());
    lower->reserve(kChunkSize);
    upper->reserve(kChunkSize);
    chunks_[c] = std::move(lower);
    chunks_.insert(chunks_.begin() + static_cast<std::ptrdiff_t>(c) + 1, std::move(upper));
    if (index > chunks_[c]->size()) {
      index -= chunks_[c]->size();
      ++c;
    }
  }
  Chunk& chunk = writableChunk(c);
  return *chunk.insert(chunk.begin() + static_cast<std::ptrdiff_t>(index), std::move(info));
}

void Model::eraseLeaf(const PatchKey& key) {
  const PatchInfo& info = at(key);
  const auto parentKey = key.parent();
  if (!info.isLeaf() || !parentKey) {
    throw Error(ErrorCode::InvalidArgument,
                "patch " + key.toString() + " is not a leaf below the root: it cannot be removed");
  }
  edit(*parentKey).childMask &=
      static_cast<std::uint8_t>(~(1u << static_cast<int>(key.quadrant())));
  const Place place = locate(key);
  Chunk& chunk = writableChunk(place.chunk);
  chunk.erase(chunk.begin() + static_cast<std::ptrdiff_t>(place.index));
  --size_;
  grids_.erase(key);
  // An emptied chunk goes; one left small joins its successor when the two fit in one chunk, so
  // erasing leaves no trail of tiny chunks.
  if (chunk.empty()) {
    chunks_.erase(chunks_.begin() + static_cast<std::ptrdiff_t>(place.chunk));
  } else if (chunk.size() < kChunkSize / 4 && place.chunk + 1 < chunks_.size() &&
             chunk.size() + chunks_[place.chunk + 1]->size() <= kChunkSize) {
    const Chunk& next = *chunks_[place.chunk + 1];
    chunk.insert(chunk.end(), next.begin(), next.end());
    chunks_.erase(chunks_.begin() + static_cast<std::ptrdiff_t>(place.chunk) + 1);
  }
}

std::vector<Model::Run> Model::runs() const {
  std::vector<Run> runs;
  runs.reserve(chunks_.size());
  for (std::size_t c = 0; c < chunks_.size(); ++c) {
    runs.push_back(
        {chunks_[c], Patches::iterator(&chunks_, c, 0), Patches::iterator(&chunks_, c + 1, 0)});
  }
  return runs;
}

std::shared_ptr<const void> Model::runOf(const PatchKey& key) const {
  const Place place = locate(key);
  return place.found ? chunks_[place.chunk] : nullptr;
}

std::vector<PatchKey> Model::children(const PatchKey& key) const {
  std::vector<PatchKey> result;
  const PatchInfo& info = at(key);
  for (const Quadrant q : kQuadrants) {
    if (info.hasChild(q)) {
      result.push_back(key.child(q));
    }
  }
  return result;
}

std::vector<PatchKey> Model::leaves() const {
  std::vector<PatchKey> result;
  for (const auto& [key, info] : patches()) {
    if (info.isLeaf()) {
      result.push_back(key);
    }
  }
  return result;
}

std::vector<PatchKey> Model::leavesWhere(const std::function<bool(const Box3d&)>& meets) const {
  std::vector<PatchKey> leaves;
  std::vector<PatchKey> pending{PatchKey::root()};
  while (!pending.empty()) {
    const PatchKey key = pending.back();
    pending.pop_back();
    const PatchInfo* info = find(key);
    if (info == nullptr || !meets(info->globalBox)) {
      continue;
    }
    if (info->isLeaf()) {
      leaves.push_back(key);
    } else {
      for (const PatchKey& child : children(key)) {
        pending.push_back(child);
      }
    }
  }
  std::sort(leaves.begin(), leaves.end());
  return leaves;
}

Box3d Model::childrenBox(const PatchKey& key) const {
  Box3d box;
  for (const Quadrant q : kQuadrants) {
    if (const PatchInfo* child = find(key.child(q))) {
      box.extend(child->globalBox);
    }
  }
  return box;
}

void Model::describe(const PatchKey& key, const PatchGrid& grid) {
  PatchInfo& info = edit(key);
  if (grid.size() != gridSize_) {
    throw Error(ErrorCode::InvalidArgument, "grid size differs from the model's patch size");
  }
  const Box3d children = childrenBox(key);
  const PatchGrid::Summary summary = grid.summarize();
  info.localBox = summary.localBox;
  info.globalBox = grid.local2global().isTranslation()
                       ? transformBox(grid.local2global(), summary.localBox)
                       : grid.globalBox();
  info.globalBox.extend(children);
  info.localBox.extend(transformBox(grid.local2global().inverse(), children));
  info.setLocal2Global(grid.local2global());
  info.resolution = summary.resolution;
  info.stored = summary.definedRect;
}

void Model::setGrid(const PatchKey& key, std::shared_ptr<const PatchGrid> grid) {
  describe(key, *grid);
  ++edit(key).version;
  attachGrid(key, std::move(grid));
  markChanged(key);
}

void Model::attachGrid(const PatchKey& key, std::shared_ptr<const PatchGrid> grid) {
  at(key);  // throws for a key not in the model
  grids_[key] = std::move(grid);
}

std::shared_ptr<const PatchGrid> Model::grid(const PatchKey& key) const {
  const auto it = grids_.find(key);
  return it != grids_.end() ? it->second : nullptr;
}

void Model::markChanged(const PatchKey& key) {
  edit(key).dirty = true;
  for (auto parent = key.parent(); parent; parent = parent->parent()) {
    edit(*parent).stale = true;
  }
}

void Model::refreshStale(const GridLoader& load) {
  std::vector<PatchKey> stale;
  for (const auto& [key, info] : patches()) {
    if (info.stale) {
      stale.push_back(key);
    }
  }
  // Deepest first, so every child is fresh before its parent is reduced from it.
  std::sort(stale.begin(), stale.end(),
            [](const PatchKey& a, const PatchKey& b) { return a.depth > b.depth; });
  for (const PatchKey& key : stale) {
    std::array<std::shared_ptr<const PatchGrid>, 4> held;
    std::array<const PatchGrid*, 4> children{};
    for (const Quadrant q : kQuadrants) {
      if (const PatchInfo* child = find(key.child(q))) {
        std::shared_ptr<const PatchGrid> attached = grid(child->key);
        held[static_cast<int>(q)] = attached ? std::move(attached) : load(*child);
        children[static_cast<int>(q)] = held[static_cast<int>(q)].get();
      }
    }
    setGrid(key, std::make_shared<const PatchGrid>(reduce(children)));
    edit(key).stale = false;
  }
}

std::vector<LevelSummary> Model::levels() const {
  std::vector<LevelSummary> levels(static_cast<std::size_t>(maxDepth() + 1));
  for (std::size_t d = 0; d < levels.size(); ++d) {
    levels[d].depth = static_cast<int>(d);
  }
  // Whole nanometres summed exactly (a __int128: any number of patches of up to 1e7 m, a
  // resolution no surface has), so the means are the same whichever chunks the sums were kept by.
  __extension__ using Sum = __int128;
  std::vector<Sum> nanometres(levels.size(), 0);
  std::vector<std::size_t> measured(levels.size(), 0);
  for (const std::shared_ptr<Chunk>& chunk : chunks_) {
    // Kept in the chunk when it is shared (a version and the edit over it: all but the chunks the
    // edit touched), made afresh otherwise.
    std::unique_ptr<const ChunkSums> made;
    const ChunkSums& sums = sumsOf(chunk, chunk.use_count() > 1, made);
    for (const ChunkSums::Level& part : sums.levels) {
      const auto d = static_cast<std::size_t>(part.depth);
      levels[d].patches += part.patches;
      levels[d].leaves += part.leaves;
      levels[d].hidden += part.hidden;
      levels[d].bounds.extend(part.bounds);
      nanometres[d] += part.nanometres;
      measured[d] += part.measured;
      if (part.finestLeaf > 0 &&
          (levels[d].finestLeaf == 0 || part.finestLeaf < levels[d].finestLeaf)) {
        levels[d].finestLeaf = part.finestLeaf;
      }
    }
  }
  for (std::size_t d = 0; d < levels.size(); ++d) {
    levels[d].resolution = measured[d] == 0 ? 0
                                            : static_cast<double>(nanometres[d]) /
                                                  static_cast<double>(measured[d]) * 1e-9;
  }
  return levels;
}

std::size_t Model::heapBytes(std::unordered_set<const void*>& counted) const {
  std::size_t bytes = chunks_.capacity() * sizeof(std::shared_ptr<Chunk>);
  for (const std::shared_ptr<Chunk>& chunk : chunks_) {
    if (counted.insert(chunk.get()).second) {
      std::unique_ptr<const ChunkSums> made;
      bytes += sumsOf(chunk, true, made).bytes;
    }
  }
  return bytes;
}

const Model::ChunkSums& Model::sumsOf(const std::shared_ptr<Chunk>& chunk, bool keep,
                                      std::unique_ptr<const ChunkSums>& made) {
  // Two readers of a shared chunk may both make them: the first stored wins.
  const ChunkSums* sums = chunk->sums.load(std::memory_order_acquire);
  if (sums != nullptr) {
    return *sums;
  }
  made = std::make_unique<const ChunkSums>(summarise(*chunk));
  const ChunkSums* stored = nullptr;
  if (keep && chunk->sums.compare_exchange_strong(stored, made.get(), std::memory_order_acq_rel)) {
    return *made.release();
  }
  return stored != nullptr ? *stored : *made;
}

Model::ChunkSums Model::summarise(const Chunk& chunk) {
  ChunkSums sums;
  // The chunk (its control block and vector, one block, and its patches' array), then what each
  // patch holds on the heap.
  constexpr std::size_t kOverhead = 16;
  sums.bytes = sharedBlock<Chunk> + chunk.capacity() * sizeof(PatchInfo) + kOverhead;
  for (const PatchInfo& info : chunk) {
    sums.bytes += info.ownHeapBytes();
    if (sums.levels.empty() || sums.levels.back().depth != info.key.depth) {
      sums.levels.emplace_back().depth = info.key.depth;
    }
    ChunkSums::Level& level = sums.levels.back();
    ++level.patches;
    level.leaves += info.isLeaf() ? 1 : 0;
    level.hidden += info.hidden ? 1 : 0;
    level.bounds.extend(info.globalBox);
    if (info.resolution > 0) {  // NaN is not
      level.nanometres += std::llround(std::min(info.resolution, 1e7) * 1e9);
      ++level.measured;
      if (info.isLeaf() && (level.finestLeaf == 0 || info.resolution < level.finestLeaf)) {
        level.finestLeaf = info.resolution;
      }
    }
  }
  return sums;
}

int deepestVisibleDepth(const std::vector<LevelSummary>& levels) {
  int depth = 0;
  for (const LevelSummary& level : levels) {
    if (level.patches > level.hidden) {
      depth = std::max(depth, level.depth);
    }
  }
  return depth;
}

bool anyHidden(const std::vector<LevelSummary>& levels) {
  return std::any_of(levels.begin(), levels.end(),
                     [](const LevelSummary& level) { return level.hidden > 0; });
}

bool Model::hasHiddenLevels() const {
  return anyHidden(levels());
}

bool Model::childrenHidden(const PatchKey& key) const {
  const PatchInfo& info = at(key);
  return !info.isLeaf() &&
         at(key.child(static_cast<Quadrant>(std::countr_zero(info.childMask)))).hidden;
}

std::vector<double> Model::avgGeometrySizes() const {
  const auto summary = levels();
  std::vector<double> sizes(summary.size(), 0);
  // Fill from the deepest level up so a level without measurable patches can borrow.
  double finer = 0;
  for (std::size_t i = summary.size(); i-- > 0;) {
    double value = summary[i].resolution;
    if (value <= 0) {
      value = finer > 0 ? finer * 2 : 1;
    }
    sizes[summary.size() - 1 - i] = value;
    finer = value;
  }
  return sizes;
}

namespace {

bool sameFolder(const PatchInfo& a, const PatchInfo& b) {
  char bufferA[PatchKey::kMaxText];
  char bufferB[PatchKey::kMaxText];
  return a.folder(bufferA) == b.folder(bufferB);
}

bool sameStoredPatch(const PatchInfo& a, const PatchInfo& b) {
  return &a == &b ||
         (a.version == b.version && a.childMask == b.childMask && a.hidden == b.hidden &&
          sameFolder(a, b) && a.globalBox == b.globalBox && a.localBox == b.localBox &&
          a.local2global() == b.local2global() && a.resolution == b.resolution &&
          a.stored == b.stored && a.files() == b.files());
}

}  // namespace

namespace {

/// Word-at-a-time mixing (a multiply and an xor-shift per 8 bytes), finished by splitmix64's
/// finaliser so that sums of digests stay well spread.
class Mixer {
 public:
  void add(std::uint64_t word) {
    h_ = (h_ ^ word) * 0x9e3779b97f4a7c15ull;
    h_ ^= h_ >> 29;
  }
  void add(double value) { add(std::bit_cast<std::uint64_t>(value)); }
  void add(std::string_view text) {
    add(std::uint64_t{text.size()});
    for (std::size_t i = 0; i < text.size(); i += 8) {
      std::uint64_t word = 0;
      std::memcpy(&word, text.data() + i, std::min<std::size_t>(8, text.size() - i));
      add(word);
    }
  }
  std::uint64_t finish() const {
    std::uint64_t z = h_;
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
  }

 private:
  std::uint64_t h_ = 0x243f6a8885a308d3ull;
};

}  // namespace

std::uint64_t patchDigest(const PatchInfo& info) {
  Mixer mix;
  mix.add(std::uint64_t{static_cast<std::uint32_t>(info.key.depth)} << 32 | info.childMask);
  mix.add(std::uint64_t{info.key.x} << 32 | info.key.y);
  mix.add(info.version);
  char buffer[PatchKey::kMaxText];
  mix.add(info.folder(buffer));
  for (const double v : {info.globalBox.min.x, info.globalBox.min.y, info.globalBox.min.z,
                         info.globalBox.max.x, info.globalBox.max.y, info.globalBox.max.z}) {
    mix.add(v);
  }
  for (const double v : info.local2global().m) {
    mix.add(v);
  }
  return mix.finish();
}

std::uint64_t modelDigest(const Model& model) {
  std::uint64_t sum = 0;
  for (const auto& [key, info] : model.patches()) {
    sum += patchDigest(info);
  }
  Mixer mix;
  mix.add(std::uint64_t{static_cast<std::uint32_t>(model.gridSize())});
  return sum + mix.finish();
}

ModelChange modelChange(const Model& before, const Model& after) {
  ModelChange change;
  const Model::Chunks& from = before.chunks_;
  const Model::Chunks& to = after.chunks_;
  std::size_t ac = 0, ai = 0, bc = 0, bi = 0;
  const auto advance = [](const Model::Chunks& chunks, std::size_t& c, std::size_t& i) {
    if (++i == chunks[c]->size()) {
      ++c;
      i = 0;
    }
  };
  while (ac < from.size() || bc < to.size()) {
    // Both at the start of one shared chunk: the same entries, the same nodes.
    if (ai == 0 && bi == 0 && ac < from.size() && bc < to.size() && from[ac] == to[bc]) {
      ++ac;
      ++bc;
      continue;
    }
    const PatchInfo* a = ac < from.size() ? &(*from[ac])[ai] : nullptr;
    const PatchInfo* b = bc < to.size() ? &(*to[bc])[bi] : nullptr;
    if (b == nullptr || (a != nullptr && a->key < b->key)) {
      change.removed.push_back(a->key);
      advance(from, ac, ai);
    } else if (a == nullptr || b->key < a->key) {
      change.changed.push_back(b->key);
      advance(to, bc, bi);
    } else {
      if (!sameStoredPatch(*a, *b)) {
        change.changed.push_back(b->key);
      }
      advance(from, ac, ai);
      advance(to, bc, bi);
    }
  }
  return change;
}

}  // namespace vsm::core
