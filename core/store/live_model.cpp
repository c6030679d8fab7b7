#include "core/store/live_model.hpp"

#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <ctime>

#include <algorithm>
#include <cctype>
#include <map>
#include <regex>
#include <utility>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/grid/shaded_relief.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/texture_file.hpp"
#include "core/pyramid/reduce.hpp"

namespace fs = std::filesystem;

namespace vsm::core {

ModelSnapshot::~ModelSnapshot() = default;

namespace {

/// Runs a function when the last owner lets go; a failure is logged.
class RunOnRelease {
 public:
  explicit RunOnRelease(std::function<void()> run) : run_(std::move(run)) {}
  ~RunOnRelease() {
    try {
      run_();
    } catch (const std::exception& e) {
      log::warn(std::string("releasing a model version: ") + e.what());
    }
  }
  RunOnRelease(const RunOnRelease&) = delete;
  RunOnRelease& operator=(const RunOnRelease&) = delete;

 private:
  std::function<void()> run_;
};

/// Folder of a patch version written by an edit: never the name of an imported patch, so a crash
/// leftover is recognisable (and removable) by its name alone.
std::string draftFolder(const PatchKey& key, std::uint64_t version) {
  return key.toString() + "-v" + std::to_string(version);
}

/// Folders vsm names: "d_x_y" as an import writes them, "d_x_y-vN" as an edit does.
bool isOurFolderName(const std::string& name) {
  static const std::regex pattern("[0-9]+_[0-9]+_[0-9]+(-v[0-9]+)?");
  return std::regex_match(name, pattern);
}

/// Texture tiles vsm names: "d_x_y.tif" and "d_x_y-vN.tif" in Images/Diffuse/.
bool isOurTileName(const std::string& name) {
  static const std::regex pattern("[0-9]+_[0-9]+_[0-9]+(-v[0-9]+)?\\.tif");
  return std::regex_match(name, pattern);
}

/// The file of a tile OpcWriter::writeTexture wrote for `folder` under the model at `dir`.
fs::path ourTileFile(const fs::path& dir, const std::string& folder) {
  return dir / "Images" / std::string(kTextureLayer) / (folder + ".tif");
}

/// The revision a kept hierarchy file holds, from its name ("vsm-revision-<n>.xml").
std::optional<std::uint64_t> revisionOfFile(const std::string& name) {
  static const std::regex pattern("vsm-revision-([0-9]{1,19})\\.xml");
  std::smatch match;
  if (!std::regex_match(name, match, pattern)) {
    return std::nullopt;
  }
  return std::stoull(match[1].str());
}

/// The kept revision files under `patches` by revision number.
std::map<std::uint64_t, fs::path> revisionFiles(const fs::path& patches) {
  std::map<std::uint64_t, fs::path> files;
  for (const auto& entry : fs::directory_iterator(patches)) {
    if (const auto n = revisionOfFile(entry.path().filename().string());
        n && entry.is_regular_file()) {
      files.emplace(*n, entry.path());
    }
  }
  return files;
}

/// Now, UTC, ISO 8601 to the second.
std::string utcNow() {
  const std::time_t now = std::time(nullptr);
  std::tm utc{};
  gmtime_r(&now, &utc);
  char text[32];
  std::strftime(text, sizeof text, "%Y-%m-%dT%H:%M:%SZ", &utc);
  return text;
}

/// The modification time of `file`, UTC, ISO 8601; empty when it cannot be read.
std::string fileTime(const fs::path& file) {
  struct stat st {};
  if (::stat(file.c_str(), &st) != 0) {
    return {};
  }
  std::tm utc{};
  gmtime_r(&st.st_mtim.tv_sec, &utc);
  char text[32];
  std::strftime(text, sizeof text, "%Y-%m-%dT%H:%M:%SZ", &utc);
  return text;
}

/// A snapshot of one revision read from its hierarchy (the current one or a kept file).
std::shared_ptr<ModelSnapshot> snapshotOf(OpcRevision read, const fs::path& hierarchyFile) {
  auto snapshot = std::make_shared<ModelSnapshot>();
  // The published version is the newest patch version: every publish gives the patches it changes
  // version (published + 1), so every process reading the directory, and every opening after a
  // restart, names the same content by the same version.
  for (const auto& [key, info] : read.model.patches()) {
    snapshot->version = std::max(snapshot->version, info.version);
  }
  if (read.record) {
    snapshot->revision = std::move(*read.record);
  } else {
    snapshot->revision.time = fileTime(hierarchyFile);
    for (const auto& [key, info] : read.model.patches()) {
      snapshot->revision.changed += info.version == snapshot->version ? 1 : 0;
    }
  }
  snapshot->model = std::make_shared<const Model>(std::move(read.model));
  return snapshot;
}

/// Removes patch folders (and the tiles vsm named for them) that no kept revision names any more.
void removeFolders(const fs::path& dir, const std::set<std::string>& folders) {
  const fs::path patches = patchesDirOf(dir);
  for (const std::string& folder : folders) {
    std::error_code ec;
    fs::remove_all(patches / folder, ec);
    // Only a tile vsm named for one of its folders is the folder's own (foreign OPCs may share
    // one).
    if (!ec && isOurFolderName(folder)) {
      fs::remove(ourTileFile(dir, folder), ec);
    }
    if (ec) {
      log::warn("cannot remove " + folder + " of a dropped revision: " + ec.message() +
                " (the next open removes it)");
    }
  }
}

/// Deepest first, keeping the order within a depth: children before their parents.
void sortDeepestFirst(std::vector<PatchKey>& keys) {
  std::stable_sort(keys.begin(), keys.end(),
                   [](const PatchKey& a, const PatchKey& b) { return a.depth > b.depth; });
}

/// A texture entry as readers resolve it: either slash, any letter case ("Diffuse/2_0_1.TIF" and
/// "diffuse\\2_0_1.tif" name the same file).
std::string normalisedEntry(std::string entry) {
  for (char& c : entry) {
    c = c == '/' ? '\\' : static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  }
  return entry;
}

}  // namespace

/// The PatchStore of one LiveModel: knows where every live version of every patch is stored.
class LiveModel::Store final : public PatchStore {
 public:
  Store(fs::path dir, PatchCache& cache, const std::string& name, int gridSize,
        std::uint64_t texturePixels)
      : dir_(std::move(dir)), cache_(cache), shape_(gridSize), texturePixels_(texturePixels) {
    id_ = cache_.addModel(name, *this);
  }
  ~Store() override {
    try {
      cache_.removeModel(id_);
    } catch (const std::exception& e) {
      log::error(std::string("closing model: ") + e.what());
    }
  }

  PatchCache& cache() { return cache_; }
  std::uint64_t texturePixels() const { return texturePixels_; }
  PatchCache::ModelId id() const { return id_; }
  const fs::path& dir() const { return dir_; }

  /// Makes a version loadable (published or draft).
  void add(const PatchInfo& info) {
    PatchInfo copy = info;
    copy.grid.reset();
    std::lock_guard lock(mutex_);
    versions_[{info.key, info.version}] = std::move(copy);
  }
  void forget(const PatchKey& key, std::uint64_t version) {
    std::lock_guard lock(mutex_);
    versions_.erase({key, version});
  }
  /// Forgets every version stored in one of `folders` and drops its cached data.
  void forgetFolders(const std::set<std::string>& folders) {
    std::vector<std::pair<PatchKey, std::uint64_t>> gone;
    {
      std::lock_guard lock(mutex_);
      for (auto it = versions_.begin(); it != versions_.end();) {
        if (folders.count(it->second.folder) != 0) {
          gone.push_back(it->first);
          it = versions_.erase(it);
        } else {
          ++it;
        }
      }
    }
    for (const auto& [key, version] : gone) {
      cache_.invalidate(id_, {key, version, MemoryCategory::Positions});
      cache_.invalidate(id_, {key, version, MemoryCategory::Textures});
    }
  }

  std::size_t expectedBytes(const ObjectId& id) const override {
    const auto n = static_cast<std::size_t>(shape_.gridSize());
    return id.category == MemoryCategory::Textures ? (n - 1) * (n - 1) * TextureTile::kChannels
                                                   : n * n * 3 * sizeof(float);
  }

  CacheValue load(const ObjectId& id) override {
    const PatchInfo info = lookup(id);
    if (id.category == MemoryCategory::Textures) {
      auto tile =
          std::make_shared<const TextureTile>(readPatchTextureTile(dir_, info, texturePixels_));
      const std::size_t bytes = tile->bytes();
      return {std::move(tile), bytes};
    }
    auto grid = std::make_shared<const PatchGrid>(readPatchGrid(dir_, shape_, info));
    const std::size_t bytes = grid->bytes();
    return {std::move(grid), bytes};
  }

  void writeBack(const ObjectId& id, const CacheValue& value) override {
    PatchInfo info = lookup(id);
    // Only drafts are ever dirty: their folders are invisible until publish() makes them durable
    // (the edit's FileSystemSync) before the hierarchy names them, so no fsync or temp file per
    // file here.
    OpcWriter writer(dir_, OpcWriter::Durability::Deferred);
    if (id.category == MemoryCategory::Textures) {
      writer.writeTexture(info, *value.object.as<TextureTile>());
      return;
    }
    // The edit described the patch after its children: its box already holds theirs. A textured
    // draft names its tile, written by its own entry's write-back.
    writer.writePatch(info, *value.object.as<PatchGrid>(), info.globalBox);
  }

 private:
  PatchInfo lookup(const ObjectId& id) const {
    std::lock_guard lock(mutex_);
    const auto it = versions_.find({id.key, id.version});
    if (it == versions_.end()) {
      throw Error(ErrorCode::NotFound, "patch " + id.key.toString() + " version " +
                                           std::to_string(id.version) + " is not stored");
    }
    return it->second;
  }

  fs::path dir_;
  PatchCache& cache_;
  PatchCache::ModelId id_ = 0;
  /// An empty model of the right patch size: what readPatchGrid needs to know of the model.
  const Model shape_;
  mutable std::mutex mutex_;  // guards versions_
  std::map<std::pair<PatchKey, std::uint64_t>, PatchInfo> versions_;
  const std::uint64_t texturePixels_;
};

// ---- LiveModel -------------------------------------------------------------------------------

std::unique_ptr<LiveModel> LiveModel::open(const fs::path& dir, std::string name, PatchCache& cache,
                                           Access access, std::uint64_t texturePixels) {
  if (access == Access::Read) {
    return load(dir, std::move(name), cache, nullptr, false, texturePixels);
  }
  patchesDirOf(dir);  // NotFound for a directory without an OPC, before anything is created
  std::shared_ptr<const durable::WriterLock> lock;
  try {
    lock = durable::WriterLock::acquire(dir);
  } catch (const Error& e) {
    const bool unwritable = e.code() == ErrorCode::Io && ::access(dir.c_str(), W_OK) != 0;
    if (access != Access::WriteIfPossible || (e.code() != ErrorCode::Conflict && !unwritable)) {
      throw;
    }
    auto model = load(dir, std::move(name), cache, nullptr, false, texturePixels);
    model->readOnlyReason_ = e.what();
    return model;
  }
  return load(dir, std::move(name), cache, std::move(lock), true, texturePixels);
}

std::unique_ptr<LiveModel> LiveModel::reopen() const {
  return load(dir_, name_, store_->cache(), lock_, false, texturePixels());
}

std::unique_ptr<LiveModel> LiveModel::load(const fs::path& dir, std::string name, PatchCache& cache,
                                           std::shared_ptr<const durable::WriterLock> lock,
                                           bool sweep, std::uint64_t texturePixels) {
  // Stamped before reading: a publish during the read leaves a stamp that differs from the file's.
  const std::optional<HierarchyStamp> stamp = hierarchyStamp(dir);
  const fs::path patches = patchesDirOf(dir);
  std::shared_ptr<ModelSnapshot> snapshot =
      snapshotOf(readOpcRevision(dir), patches / "patchhierarchy.xml");
  const Model& model = *snapshot->model;
  if (lock != nullptr) {
    // A publish interrupted after its commit point left these undone; they are idempotent.
    finishHierarchy(dir);
  }
  if (sweep) {
    // Leftovers of edits interrupted by a crash or a failure: folders named like ours that no kept
    // revision names (unpublished drafts, or a dropped revision's folders when the crash came
    // between its hierarchy's removal and theirs), revision files newer than the current one, and
    // temporary files of interrupted writes. Only the lock holder may do this: another writer's
    // drafts look the same.
    std::set<std::string> named;
    std::set<std::string> namedTiles;
    for (const auto& [key, info] : model.patches()) {
      named.insert(info.folder);
      if (!info.textureFile.empty()) {
        namedTiles.insert(normalisedEntry(info.textureFile));
      }
    }
    std::vector<fs::path> orphans;
    for (const auto& [number, file] : revisionFiles(patches)) {
      if (number > snapshot->version) {
        orphans.push_back(file);
        continue;
      }
      for (const std::string& folder : namedFolders(file)) {
        named.insert(folder);
        namedTiles.insert(normalisedEntry(textureEntryFor(folder)));
      }
    }
    for (const auto& entry : fs::directory_iterator(patches)) {
      const std::string folder = entry.path().filename().string();
      if ((entry.is_directory() && isOurFolderName(folder) && named.count(folder) == 0) ||
          (entry.is_regular_file() && durable::isTempFileName(folder))) {
        orphans.push_back(entry.path());
      }
    }
    const fs::path tiles = dir / "Images" / std::string(kTextureLayer);
    if (fs::is_directory(tiles)) {
      for (const auto& entry : fs::directory_iterator(tiles)) {
        const std::string file = entry.path().filename().string();
        if (entry.is_regular_file() &&
            ((isOurTileName(file) && namedTiles.count(normalisedEntry(
                                         textureEntryFor(file.substr(0, file.size() - 4)))) == 0) ||
             durable::isTempFileName(file))) {
          orphans.push_back(entry.path());
        }
      }
    }
    for (const fs::path& orphan : orphans) {
      log::info("model=" + name + " removing leftover " + orphan.filename().string());
      std::error_code ec;
      fs::remove_all(orphan, ec);
      if (ec) {
        log::warn("model=" + name + " cannot remove leftover " + orphan.string() + ": " +
                  ec.message() + " (retried at the next open)");
      }
    }
  }

  auto store = std::make_shared<Store>(dir, cache, name, model.gridSize(), texturePixels);
  for (const auto& [key, info] : model.patches()) {
    store->add(info);
  }
  const std::uint64_t version = snapshot->version;
  auto live = std::unique_ptr<LiveModel>(
      new LiveModel(dir, std::move(name), std::move(store), snapshot, std::move(lock)));
  live->revisionSnapshots_[version] = snapshot;
  live->readStamp_ = stamp;
  return live;
}

LiveModel::LiveModel(fs::path dir, std::string name, std::shared_ptr<Store> store,
                     std::shared_ptr<ModelSnapshot> snapshot,
                     std::shared_ptr<const durable::WriterLock> lock)
    : dir_(std::move(dir)),
      name_(std::move(name)),
      store_(std::move(store)),
      snapshot_(std::move(snapshot)),
      lock_(std::move(lock)) {}

LiveModel::~LiveModel() = default;

bool LiveModel::changedOnDisk() const {
  return hierarchyStamp(dir_) != readStamp_;
}

std::uint64_t LiveModel::texturePixels() const {
  return store_->texturePixels();
}

std::shared_ptr<const ModelSnapshot> LiveModel::snapshot() const {
  std::lock_guard lock(mutex_);
  return snapshot_;
}

std::string revisionFileName(std::uint64_t number) {
  return "vsm-revision-" + std::to_string(number) + ".xml";
}

std::shared_ptr<const ModelSnapshot> LiveModel::heldSnapshot(std::uint64_t revision) const {
  std::lock_guard lock(mutex_);
  if (snapshot_->version == revision) {
    return snapshot_;
  }
  if (const auto it = revisionSnapshots_.find(revision); it != revisionSnapshots_.end()) {
    return it->second.lock();
  }
  return nullptr;
}

std::shared_ptr<const ModelSnapshot> LiveModel::snapshotAt(std::uint64_t revision) {
  if (auto held = heldSnapshot(revision)) {
    return held;
  }
  std::shared_ptr<const ModelSnapshot> current = snapshot();
  const fs::path file = patchesDirOf(dir_) / revisionFileName(revision);
  if (revision > current->version || !fs::is_regular_file(file)) {
    throw Error(ErrorCode::NotFound, "model '" + name_ + "' keeps no revision " +
                                         std::to_string(revision) + " (GET its revisions)");
  }
  std::shared_ptr<ModelSnapshot> read =
      snapshotOf(readOpcRevision(dir_, file.filename().string()), file);
  if (read->version != revision || read->model->gridSize() != current->model->gridSize()) {
    throw Error(ErrorCode::Corrupt, file.string() + " does not hold revision " +
                                        std::to_string(revision) + " of this model");
  }
  for (const auto& [key, info] : read->model->patches()) {
    store_->add(info);
  }
  {
    std::lock_guard lock(mutex_);
    revisionSnapshots_[revision] = read;
    recentRevisions_.push_back(read);
    if (recentRevisions_.size() > 2) {
      recentRevisions_.pop_front();
    }
  }
  // A publish that dropped the revision meanwhile removed its file before looking for snapshots
  // of it to hand its folders to: either it found this one, or the file is gone now.
  if (!fs::exists(file)) {
    std::lock_guard lock(mutex_);
    std::erase(recentRevisions_, read);
    throw Error(ErrorCode::NotFound,
                "model '" + name_ + "' no longer keeps revision " + std::to_string(revision));
  }
  return read;
}

std::vector<RevisionSummary> LiveModel::revisions() const {
  const std::shared_ptr<const ModelSnapshot> current = snapshot();
  std::vector<RevisionSummary> list;
  for (const auto& [number, file] : revisionFiles(patchesDirOf(dir_))) {
    if (number >= current->version) {
      continue;
    }
    {
      std::lock_guard lock(mutex_);
      if (const auto it = revisionSnapshots_.find(number); it != revisionSnapshots_.end()) {
        if (const auto held = it->second.lock()) {
          list.push_back({number, held->revision, false});
          continue;
        }
      }
    }
    // The record alone: the hierarchy file without the patches' metadata.
    RevisionRecord record = readRevisionRecord(file).value_or(RevisionRecord{});
    if (record.time.empty()) {
      record.time = fileTime(file);
    }
    list.push_back({number, std::move(record), false});
  }
  list.push_back({current->version, current->revision, true});
  return list;
}

PatchCache::Pin LiveModel::positions(const ModelSnapshot& snapshot, const PatchKey& key) {
  const PatchInfo& info = snapshot.model->at(key);
  return store_->cache().get(store_->id(), {key, info.version, MemoryCategory::Positions});
}

PatchCache::Pin LiveModel::texture(const ModelSnapshot& snapshot, const PatchKey& key) {
  const PatchInfo& info = snapshot.model->at(key);
  if (info.textureFile.empty()) {
    return {};
  }
  return store_->cache().get(store_->id(), {key, info.version, MemoryCategory::Textures});
}

void LiveModel::onPublish(std::function<void(const ReplacedVersions&)> observer) {
  std::lock_guard lock(mutex_);
  onPublish_ = std::move(observer);
}

void LiveModel::onNewVersion(NewVersionObserver observer) {
  std::lock_guard lock(mutex_);
  onNewVersion_ = std::move(observer);
}

std::unique_ptr<ModelEdit> LiveModel::beginEdit() {
  if (lock_ == nullptr) {
    throw Error(ErrorCode::Conflict,
                "model '" + name_ + "' is open for reading only" +
                    (readOnlyReason_.empty() ? std::string() : ": " + readOnlyReason_));
  }
  bool expected = false;
  if (!editing_.compare_exchange_strong(expected, true)) {
    throw Error(ErrorCode::Conflict, "model '" + name_ + "' is being changed by another job");
  }
  try {
    return std::unique_ptr<ModelEdit>(new ModelEdit(*this, snapshot()));
  } catch (...) {
    editing_ = false;
    throw;
  }
}

// ---- ModelEdit -------------------------------------------------------------------------------

ModelEdit::ModelEdit(LiveModel& live, std::shared_ptr<const ModelSnapshot> base)
    : live_(live),
      sync_(live.dir_),
      base_(std::move(base)),
      model_(std::make_unique<Model>(*base_->model)) {}

ModelEdit::~ModelEdit() {
  if (!published_) {
    // Discard: the drafts leave the cache unwritten and their folders (if evicted) go.
    LiveModel::Store& store = *live_.store_;
    for (const PatchKey& key : changed_) {
      const ObjectId id = draftId(key);
      try {
        store.cache().drop(store.id(), id);
        store.cache().drop(store.id(), {key, id.version, MemoryCategory::Textures});
        const std::string folder = draftFolder(key, id.version);
        fs::remove_all(patchesDirOf(live_.dir_) / folder);
        fs::remove(ourTileFile(live_.dir_, folder));
      } catch (const std::exception& e) {
        log::warn("model=" + live_.name_ + " discarding " + key.toString() + ": " + e.what());
      }
      store.forget(key, id.version);
    }
  }
  live_.editing_ = false;
}

ObjectId ModelEdit::draftId(const PatchKey& key) const {
  // The version this edit publishes: above every patch version on disk (the published version is
  // their maximum), so a draft's folder never names a published one.
  return {key, base_->version + 1, MemoryCategory::Positions};
}

PatchCache::Pin ModelEdit::positions(const PatchKey& key) {
  const PatchInfo& info = model_->at(key);
  return live_.store_->cache().get(live_.store_->id(),
                                   {key, info.version, MemoryCategory::Positions});
}

PatchCache::Pin ModelEdit::texture(const PatchKey& key) {
  const PatchInfo& info = model_->at(key);
  if (info.textureFile.empty()) {
    return {};
  }
  return live_.store_->cache().get(live_.store_->id(),
                                   {key, info.version, MemoryCategory::Textures});
}

void ModelEdit::setPositions(const PatchKey& key, std::shared_ptr<const PatchGrid> grid,
                             std::shared_ptr<const TextureTile> texture) {
  if (grid->size() != model_->gridSize()) {
    throw Error(ErrorCode::InvalidArgument, "patch " + key.toString() + " has a grid of " +
                                                std::to_string(grid->size()) + " instead of " +
                                                std::to_string(model_->gridSize()));
  }
  if (texture && texture->size() != textureTileSize(model_->gridSize())) {
    throw Error(ErrorCode::InvalidArgument,
                "patch " + key.toString() + " has a texture tile of " +
                    std::to_string(texture->size()) + " texels instead of " +
                    std::to_string(textureTileSize(model_->gridSize())));
  }
  if (model_->find(key) == nullptr) {
    PatchInfo info;
    info.key = key;
    model_->insert(std::move(info));
  }
  const ObjectId id = draftId(key);
  const ObjectId textureId{key, id.version, MemoryCategory::Textures};
  PatchInfo& info = model_->at(key);
  LiveModel::Store& store = *live_.store_;
  if (!texture && changed_.count(key) != 0 && !info.textureFile.empty()) {
    // This edit's earlier texture of the patch is obsolete (and may have been written already).
    store.cache().drop(store.id(), textureId);
    fs::remove(ourTileFile(live_.dir_, info.folder));
  }
  info.version = id.version;
  info.folder = draftFolder(key, id.version);
  info.positionsFile = "Positions.aara";
  info.coordinatesFile.clear();
  info.textureFile = texture ? textureEntryFor(info.folder) : std::string();
  model_->describe(key, *grid);
  model_->markChanged(key);
  info.dirty = false;  // the cache tracks dirtiness; the model only needs `changed_`
  changed_.insert(key);
  store.add(info);
  const std::size_t bytes = grid->bytes();
  store.cache().put(store.id(), id, {std::move(grid), bytes}, true);
  if (texture) {
    const std::size_t textureBytes = texture->bytes();
    store.cache().put(store.id(), textureId, {std::move(texture), textureBytes}, true);
  }
}

void ModelEdit::writeEarly(const PatchKey& key) {
  // Only the cache and the store's own (locked) table are touched: setPositions of other keys may
  // run meanwhile.
  const ObjectId id = draftId(key);
  LiveModel::Store& store = *live_.store_;
  store.cache().flush(store.id(), id);
  store.cache().flush(store.id(), {key, id.version, MemoryCategory::Textures});
}

void ModelEdit::refreshStale(const CancelToken* cancel) {
  std::vector<PatchKey> stale;
  for (const auto& [key, info] : model_->patches()) {
    if (info.stale) {
      stale.push_back(key);
    }
  }
  // Deepest first, so every child is final before its parent is reduced from it.
  sortDeepestFirst(stale);
  for (const PatchKey& key : stale) {
    if (cancel != nullptr) {
      cancel->throwIfCancelled();
    }
    std::shared_ptr<const PatchGrid> parent;
    std::shared_ptr<const TextureTile> parentTexture;
    // A child without a tile of this model's size (none, or a foreign one of another size)
    // counts with its shaded relief, computed while its grid is held anyway.
    std::array<std::optional<TextureTile>, 4> reliefs;
    {
      std::array<PatchCache::Pin, 4> pins;
      std::array<const PatchGrid*, 4> children{};
      for (const Quadrant q : kQuadrants) {
        const PatchKey child = key.child(q);
        if (const PatchInfo* info = model_->find(child)) {
          auto& pin = pins[static_cast<int>(q)];
          pin = positions(child);
          children[static_cast<int>(q)] = pin.get<PatchGrid>().get();
          if (info->textureFile.empty()) {
            reliefs[static_cast<int>(q)].emplace(shadedRelief(*children[static_cast<int>(q)]));
          }
        }
      }
      parent = std::make_shared<const PatchGrid>(reduce(children));
    }
    {
      // The parent's tile from its children's, one at a time as the grids.
      const int size = textureTileSize(model_->gridSize());
      std::array<PatchCache::Pin, 4> pins;
      std::array<const TextureTile*, 4> children{};
      for (const Quadrant q : kQuadrants) {
        const PatchKey child = key.child(q);
        const int i = static_cast<int>(q);
        if (model_->find(child) == nullptr) {
          continue;
        }
        if (!reliefs[i]) {
          pins[i] = texture(child);
          if (pins[i].get<TextureTile>()->size() == size) {
            children[i] = pins[i].get<TextureTile>().get();
            continue;
          }
          pins[i] = {};
          const PatchCache::Pin grid = positions(child);
          reliefs[i].emplace(shadedRelief(*grid.get<PatchGrid>()));
        }
        children[i] = &*reliefs[i];
      }
      parentTexture = std::make_shared<const TextureTile>(downsampleQuadrants(children, size));
    }
    setPositions(key, std::move(parent), std::move(parentTexture));
    model_->at(key).stale = false;
  }
}

void ModelEdit::restore(const ModelSnapshot& from, const CancelToken* cancel) {
  const Model& target = *from.model;
  if (target.gridSize() != model_->gridSize()) {
    throw Error(ErrorCode::InvalidArgument, "a revision of another patch size cannot be restored");
  }
  // Deepest first: what `from` does not hold goes, leaves before their parents.
  std::vector<PatchKey> keys;
  for (const auto& [key, info] : model_->patches()) {
    keys.push_back(key);
  }
  sortDeepestFirst(keys);
  for (const PatchKey& key : keys) {
    if (target.find(key) == nullptr) {
      model_->eraseLeaf(key);
      live_.store_->cache().drop(live_.store_->id(), draftId(key));
      if (base_->model->find(key) != nullptr) {
        removed_.insert(key);
      }
      changed_.erase(key);
    }
  }
  // Parents first, what the edit lacks is placed (its data follows), so that the data can then go
  // in deepest first: a patch's box holds its children's final boxes.
  std::set<PatchKey> placed;
  for (const auto& [key, info] : target.patches()) {
    if (model_->find(key) == nullptr) {
      PatchInfo placeholder;
      placeholder.key = key;
      model_->insert(std::move(placeholder));
      placed.insert(key);
    }
  }
  keys.clear();
  for (const auto& [key, info] : target.patches()) {
    if (placed.count(key) != 0 || model_->at(key).version != info.version ||
        changed_.count(key) != 0) {
      keys.push_back(key);
    }
  }
  sortDeepestFirst(keys);
  for (const PatchKey& key : keys) {
    if (cancel != nullptr) {
      cancel->throwIfCancelled();
    }
    std::shared_ptr<const PatchGrid> grid = live_.positions(from, key).get<PatchGrid>();
    std::shared_ptr<const TextureTile> texture;
    if (PatchCache::Pin pin = live_.texture(from, key)) {
      texture = pin.get<TextureTile>();
    }
    setPositions(key, std::move(grid), std::move(texture));
  }
  // Every overview is `from`'s own now: none is recomputed.
  for (auto& [key, info] : target.patches()) {
    model_->at(key).stale = false;
  }
}

void ModelEdit::publish(const CancelToken* cancel, const PublishOptions& options) {
  if (published_) {
    throw Error(ErrorCode::Conflict, "edit already published");
  }
  if (options.keepRevisions < 2) {
    throw Error(ErrorCode::InvalidArgument,
                "at least 2 revisions are kept (the previous one while replicas follow), not " +
                    std::to_string(options.keepRevisions));
  }
  if (changed_.empty() && removed_.empty()) {
    throw Error(ErrorCode::InvalidArgument, "the edit changes nothing: no new revision");
  }
  refreshStale(cancel);
  if (cancel != nullptr) {
    cancel->throwIfCancelled();
  }
  LiveModel::Store& store = *live_.store_;
  // 1. Every changed patch into its new folder (evicted ones were written already), durable.
  // Flushers take distinct dirty entries, so several run side by side.
  runTasks(options.executor,
           std::vector<std::function<void()>>(options.executor != nullptr ? kPublishWriters : 1,
                                              [&] { store.cache().flush(store.id()); }));
  sync_.sync();
  if (cancel != nullptr) {
    cancel->throwIfCancelled();
  }
  // 2. The base revision's hierarchy kept under its own name (once), durable before the commit
  // point: from then on its folders are named by a kept revision. Then the new hierarchy naming
  // the new folders, fsynced under a temporary name, and everything the switch to the new version
  // needs, prepared so that nothing after the commit point can fail but its durability.
  const fs::path patches = patchesDirOf(live_.dir_);
  const std::string baseName = revisionFileName(base_->version);
  if (!fs::exists(patches / baseName)) {
    stageHierarchy(live_.dir_, *base_->model, &base_->revision, baseName)->commit();
    durable::syncDirectory(patches);
  }
  const std::uint64_t version = base_->version + 1;
  auto next = std::make_shared<Model>(*model_);
  auto snapshot = std::make_shared<ModelSnapshot>();
  snapshot->revision = {base_->version,  utcNow(),        options.job,
                        changed_.size(), removed_.size(), options.restoredFrom};
  const std::unique_ptr<durable::PendingFile> hierarchy =
      stageHierarchy(live_.dir_, *next, &snapshot->revision);
  snapshot->model = std::move(next);
  snapshot->version = version;

  // 3. The commit point: from the rename on, the new version is the model's.
  hierarchy->commit();
  published_ = true;
  {
    std::lock_guard lock(live_.mutex_);
    live_.snapshot_ = snapshot;
    live_.revisionSnapshots_[version] = snapshot;
  }
  // What others derived from the replaced versions may go now (see LiveModel::onPublish).
  std::function<void(const LiveModel::ReplacedVersions&)> observer;
  LiveModel::NewVersionObserver announce;
  {
    std::lock_guard lock(live_.mutex_);
    observer = live_.onPublish_;
    announce = live_.onNewVersion_;
  }
  if (observer) {
    LiveModel::ReplacedVersions replaced;
    for (const PatchKey& key : changed_) {
      if (const PatchInfo* old = base_->model->find(key)) {
        replaced.emplace_back(key, old->version);
      }
    }
    for (const PatchKey& key : removed_) {
      replaced.emplace_back(key, base_->model->at(key).version);
    }
    observer(replaced);
  }
  if (announce) {
    announce(version, changed_);
  }

  // 4. Reported, never undone; the next open retries it.
  try {
    finishHierarchy(live_.dir_);
  } catch (const Error& e) {
    throw Error(ErrorCode::Io, "version " + std::to_string(version) + " of model '" + live_.name_ +
                                   "' is published, but " + e.what() +
                                   " (retried at the next open)");
  }
  // 5. Revisions beyond the count go, oldest first.
  live_.dropRevisions(version, *snapshot->model, options.keepRevisions);
}

void LiveModel::dropRevisions(std::uint64_t current, const Model& latest, unsigned keep) {
  try {
    const fs::path patches = patchesDirOf(dir_);
    std::map<std::uint64_t, fs::path> files = revisionFiles(patches);
    std::erase_if(files, [&](const auto& entry) { return entry.first >= current; });
    while (files.size() + 1 > keep) {
      const auto oldest = files.begin();
      const std::uint64_t number = oldest->first;
      std::set<std::string> only = namedFolders(oldest->second);
      // Folders are never shared across a gap (a restore copies), so what the next kept revision
      // does not name, no later one does.
      const auto nextFile = std::next(oldest);
      if (nextFile != files.end()) {
        for (const std::string& folder : namedFolders(nextFile->second)) {
          only.erase(folder);
        }
      } else {
        for (const auto& [key, info] : latest.patches()) {
          only.erase(info.folder);
        }
      }
      // The file first: a crash after it leaves folders no kept revision names, which the next
      // open removes; never a listed revision without its folders.
      if (::unlink(oldest->second.c_str()) != 0 && errno != ENOENT) {
        throw Error(ErrorCode::Io,
                    "cannot remove " + oldest->second.string() + ": " + std::strerror(errno));
      }
      durable::syncDirectory(patches);
      files.erase(oldest);
      log::info("model=" + name_ + " dropped revision " + std::to_string(number) + " (" +
                std::to_string(only.size()) + " folders only it used)");
      std::shared_ptr<Store> keepStore = store_;
      const fs::path dir = dir_;
      auto removal = std::make_shared<const RunOnRelease>([keepStore, dir, only] {
        keepStore->forgetFolders(only);
        removeFolders(dir, only);
      });
      std::lock_guard lock(mutex_);
      std::erase_if(recentRevisions_, [&](const auto& held) { return held->version == number; });
      if (const auto it = revisionSnapshots_.find(number); it != revisionSnapshots_.end()) {
        if (const std::shared_ptr<ModelSnapshot> held = it->second.lock()) {
          held->heldRemovals.push_back(std::move(removal));  // runs when its readers let go
        }
        revisionSnapshots_.erase(it);
      }
      // Otherwise `removal` runs here, as its last owner goes.
    }
    std::lock_guard lock(mutex_);
    std::erase_if(revisionSnapshots_, [](const auto& entry) { return entry.second.expired(); });
  } catch (const std::exception& e) {
    log::warn("model=" + name_ + " dropping old revisions: " + e.what() +
              " (retried at the next publish)");
  }
}

}  // namespace vsm::core
