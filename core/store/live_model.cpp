#include "core/store/live_model.hpp"

#include <unistd.h>

#include <algorithm>
#include <fstream>
#include <functional>
#include <iterator>
#include <map>
#include <optional>
#include <string_view>
#include <unordered_set>
#include <utility>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/opc/opc_index.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/texture_file.hpp"
#include "core/store/model_edit.hpp"
#include "core/store/model_store.hpp"
#include "core/store/store_files.hpp"

namespace fs = std::filesystem;

namespace vsm::core {

using namespace store;

ModelSnapshot::~ModelSnapshot() = default;

namespace {

/// The folders the kept revisions (`kept`: number -> hierarchy file, and the current one,
/// `current`) name and the current one does not are exactly those the publishes after the oldest
/// kept one retired, which each index's head records: calls `keep` for those, read from the heads
/// alone (a few kB each), and returns true. False, having called nothing, when a revision after
/// the oldest has no such head or its parent is not the kept revision before it: the caller reads
/// every kept revision's folders.
bool keepRetiredSinceOldest(const std::map<std::uint64_t, fs::path>& kept, std::uint64_t current,
                            const fs::path& patches,
                            const std::function<void(std::string_view)>& keep) {
  std::vector<std::pair<std::uint64_t, fs::path>> chain(kept.begin(), kept.end());
  chain.emplace_back(current, patches / "patchhierarchy.xml");
  std::vector<RetiredFolder> retired;
  for (std::size_t i = 1; i < chain.size(); ++i) {
    std::optional<IndexedRevision> head = readIndexedRevision(chain[i].second);
    if (!head || !head->record || !head->retired || head->record->parent != chain[i - 1].first) {
      return false;
    }
    retired.insert(retired.end(), std::make_move_iterator(head->retired->begin()),
                   std::make_move_iterator(head->retired->end()));
  }
  for (const RetiredFolder& r : retired) {
    keep(r.folder);
  }
  return true;
}

/// Removes what edits interrupted by a crash or a failure left: folders named like ours that no
/// kept revision names (unpublished drafts, or a dropped revision's folders when the crash came
/// between its hierarchy's removal and theirs), revision files newer than the current one, and
/// temporary files of interrupted writes. Only the lock holder may do this: another writer's
/// drafts look the same. Returns the kept revision files it found (as revisionFiles() lists them:
/// the first publish need not list Patches/ again, 1.4 million entries at 10^6 patches).
std::map<std::uint64_t, fs::path> sweepLeftovers(const fs::path& dir, const std::string& name,
                                                 const ModelSnapshot& current) {
  const fs::path patches = patchesDirOf(dir);
  const fs::path tiles = dir / "Images" / std::string(kTextureLayer);
  // By the change: the folders and tiles the current model does not name are the candidates, and
  // only they are looked up in the kept revisions (which name them when an edit replaced them).
  const NamedFolders named(*current.model);
  std::vector<fs::path> orphans;
  std::map<std::string, fs::path, std::less<>> candidates;  // folder -> its path
  std::map<std::uint64_t, fs::path> kept;                   // revision -> its hierarchy file
  std::vector<fs::path> indexes;
  std::set<std::string> hiddenFiles;  // second hierarchy files (hidden levels)
  // Folders named as their key, most of them: looked up at once, in key order, after the listing.
  std::vector<PatchKey> plain;
  for (const auto& entry : fs::directory_iterator(patches)) {
    const std::string file = entry.path().filename().string();
    if (entry.is_directory()) {
      if (const std::optional<PatchKey> key = NamedFolders::plainKey(file)) {
        plain.push_back(*key);
      } else if (!named.contains(file) && isOurFolderName(file)) {
        candidates.emplace(file, entry.path());
      }
    } else if (!entry.is_regular_file()) {
      continue;
    } else if (durable::isTempFileName(file)) {
      orphans.push_back(entry.path());
    } else if (isIndexFileName(file)) {
      indexes.push_back(entry.path());
    } else if (isHiddenHierarchyFileName(file)) {
      hiddenFiles.insert(file);
    } else if (const std::optional<std::uint64_t> number = revisionOfFile(file)) {
      if (*number > current.version) {
        orphans.push_back(entry.path());
      } else {
        kept.emplace(*number, entry.path());
      }
    }
  }
  std::sort(plain.begin(), plain.end());
  for (const PatchKey& key : named.unnamed(plain)) {
    std::string folder = key.toString();
    fs::path path = patches / folder;
    candidates.emplace(std::move(folder), std::move(path));
  }
  plain = {};
  // Indexes of no kept hierarchy file.
  std::unordered_set<std::string> keptIndexes{indexFileName("patchhierarchy.xml")};
  for (const auto& [number, file] : kept) {
    keptIndexes.insert(indexFileName(file.filename().string()));
  }
  // And the bases those indexes build on (delta indexes; the others name none).
  std::unordered_set<std::string> keptBases;
  for (const fs::path& index : indexes) {
    if (keptIndexes.contains(index.filename().string())) {
      if (const std::optional<IndexBase> base = readIndexBase(index)) {
        keptBases.insert(base->name);
      }
    }
  }
  for (const fs::path& index : indexes) {
    const std::string file = index.filename().string();
    if (!keptIndexes.contains(file) && !keptBases.contains(file)) {
      orphans.push_back(index);
    }
  }
  // Our tiles of folders the current model does not name (by the folder: the current model's own
  // tile names are its textureFile entries).
  std::map<std::string, fs::path, std::less<>> tileCandidates;  // folder -> the tile's path
  if (fs::is_directory(tiles)) {
    std::unordered_set<std::string> namedTiles;
    for (const auto& [key, info] : current.model->patches()) {
      if (!info.textureFile().empty()) {
        namedTiles.insert(normalisedEntry(info.textureFile()));
      }
    }
    for (const auto& entry : fs::directory_iterator(tiles)) {
      const std::string file = entry.path().filename().string();
      if (!entry.is_regular_file()) {
        continue;
      }
      if (durable::isTempFileName(file)) {
        orphans.push_back(entry.path());
      } else if (isOurTileName(file)) {
        std::string folder = file.substr(0, file.size() - 4);
        if (!namedTiles.contains(normalisedEntry(textureEntryFor(folder)))) {
          tileCandidates.emplace(std::move(folder), entry.path());
        }
      }
    }
  }
  const auto keep = [&](std::string_view folder) {
    if (const auto it = candidates.find(folder); it != candidates.end()) {
      candidates.erase(it);
    }
    if (const auto it = tileCandidates.find(folder); it != tileCandidates.end()) {
      tileCandidates.erase(it);
    }
  };
  if ((!candidates.empty() || !tileCandidates.empty()) &&
      !keepRetiredSinceOldest(kept, current.version, patches, keep)) {
    for (const auto& [number, file] : kept) {
      forEachNamedFolder(file, keep);
    }
  }
  for (auto* left : {&candidates, &tileCandidates}) {
    for (auto& [folder, path] : *left) {
      orphans.push_back(std::move(path));
    }
  }
  // Second hierarchy files no kept hierarchy names (a publish interrupted before its commit, or a
  // dropped revision's when the removal failed).
  if (!hiddenFiles.empty()) {
    std::vector<fs::path> hierarchies{patches / "patchhierarchy.xml"};
    for (const auto& [number, file] : kept) {
      hierarchies.push_back(file);
    }
    if (const std::size_t removed = removeUnnamedHiddenFiles(patches, hiddenFiles, hierarchies)) {
      log::info("model=" + name + " removed " + std::to_string(removed) +
                " leftover second hierarchy file" + (removed == 1 ? "" : "s"));
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
  return kept;
}

}  // namespace

std::unique_ptr<LiveModel> LiveModel::open(const fs::path& dir, std::string name, PatchCache& cache,
                                           Access access, std::uint64_t texturePixels) {
  if (access == Access::Read) {
    return load(dir, std::move(name), cache, nullptr, texturePixels);
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
    auto model = load(dir, std::move(name), cache, nullptr, texturePixels);
    model->readOnlyReason_ = e.what();
    return model;
  }
  auto writer = std::make_shared<Writer>();
  writer->lock = std::move(lock);
  return load(dir, std::move(name), cache, std::move(writer), texturePixels);
}

ModelChange changeSince(const std::shared_ptr<const Model>& before, const ModelSnapshot& after) {
  if (after.published && after.published->parent.lock() == before) {
    return after.published->change;
  }
  return modelChange(*before, *after.model);
}

std::unique_ptr<LiveModel> LiveModel::reopen() const {
  if (writer_) {
    // Read again after a failure: nothing in memory is trusted, the revision list neither.
    std::lock_guard lock(writer_->mutex);
    writer_->revisionFiles.reset();
  }
  return load(dir_, name_, store_->cache(), writer_, texturePixels(), indexBases_);
}

std::unique_ptr<LiveModel> LiveModel::load(const fs::path& dir, std::string name, PatchCache& cache,
                                           std::shared_ptr<Writer> writer,
                                           std::uint64_t texturePixels,
                                           std::shared_ptr<IndexBaseMemo> indexBases) {
  // Stamped before reading: a publish during the read leaves a stamp that differs from the file's.
  const std::optional<HierarchyStamp> stamp = hierarchyStamp(dir);
  const fs::path patches = patchesDirOf(dir);
  if (writer == nullptr && indexBases == nullptr) {
    indexBases = std::make_shared<IndexBaseMemo>();
  } else if (writer != nullptr) {
    indexBases = nullptr;
  }
  std::shared_ptr<ModelSnapshot> snapshot = snapshotOf(
      readOpcRevision(dir, "patchhierarchy.xml", indexBases.get()), patches / "patchhierarchy.xml");
  if (writer != nullptr) {
    // A publish interrupted after its commit point left these undone; they are idempotent.
    finishHierarchy(dir);
  }
  auto store = std::make_shared<Store>(dir, cache, name, snapshot->model, texturePixels);
  const std::uint64_t version = snapshot->version;
  auto live = std::unique_ptr<LiveModel>(
      new LiveModel(dir, std::move(name), std::move(store), snapshot, std::move(writer)));
  live->revisionSnapshots_[version] = snapshot;
  live->readStamp_ = stamp;
  live->revisionBases_ = indexBases != nullptr ? indexBases : std::make_shared<IndexBaseMemo>();
  live->indexBases_ = std::move(indexBases);
  return live;
}

LiveModel::LiveModel(fs::path dir, std::string name, std::shared_ptr<Store> store,
                     std::shared_ptr<ModelSnapshot> snapshot, std::shared_ptr<Writer> writer)
    : dir_(std::move(dir)),
      name_(std::move(name)),
      store_(std::move(store)),
      snapshot_(std::move(snapshot)),
      writer_(std::move(writer)) {
  if (writer_ != nullptr) {
    std::lock_guard lock(writer_->mutex);
    writer_->current = this;
    writer_->openings.push_back(this);
  }
}

LiveModel::~LiveModel() {
  if (writer_ != nullptr) {
    std::lock_guard lock(writer_->mutex);
    std::erase(writer_->openings, this);
    if (writer_->current == this) {
      // A newer opening dropped unused (its registry entry was replaced meanwhile): the newest
      // one left may edit again.
      writer_->current = writer_->openings.empty() ? nullptr : writer_->openings.back();
    }
  }
}

bool LiveModel::changedOnDisk() const {
  const std::optional<HierarchyStamp> now = hierarchyStamp(dir_);
  std::lock_guard lock(mutex_);
  return now != readStamp_;
}

std::uint64_t LiveModel::texturePixels() const {
  return store_->texturePixels();
}

namespace {

/// The path of a cache file of the model at `dir` (in Patches/, where an interrupted write's
/// temporary file is a leftover the sweep removes); throws for a name that is not "vsm-<what>.bin".
fs::path cacheFilePath(const fs::path& dir, std::string_view name) {
  const bool plain = name.find_first_of("/\\") == std::string_view::npos;
  if (!plain || !name.starts_with("vsm-") || !name.ends_with(".bin") || name.size() <= 8) {
    throw Error(ErrorCode::InvalidArgument, "not a cache file name: '" + std::string(name) + "'");
  }
  return patchesDirOf(dir) / name;
}

}  // namespace

std::optional<std::vector<std::byte>> LiveModel::readCacheFile(std::string_view name,
                                                               std::size_t maxBytes) const {
  const fs::path path = cacheFilePath(dir_, name);
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    if (!fs::exists(path)) {
      return std::nullopt;
    }
    throw Error(ErrorCode::Io, "cannot open " + path.string());
  }
  in.seekg(0, std::ios::end);
  const std::streamoff size = in.tellg();
  if (size < 0 || static_cast<std::uint64_t>(size) > maxBytes) {
    return std::nullopt;
  }
  std::vector<std::byte> bytes(static_cast<std::size_t>(size));
  in.seekg(0);
  if (!in.read(reinterpret_cast<char*>(bytes.data()), size)) {
    throw Error(ErrorCode::Io, "cannot read " + path.string());
  }
  return bytes;
}

void LiveModel::writeCacheFile(std::string_view name, std::span<const std::byte> bytes) {
  const fs::path path = cacheFilePath(dir_, name);
  if (!writable()) {
    throw Error(ErrorCode::Conflict,
                "model " + name_ + " is open for reading only: its cache files are its writer's");
  }
  removeLeftovers();  // the sweep first: it would take this write's temporary file for one
  durable::writeFileAtomically(path, bytes);
}

std::shared_ptr<const ModelSnapshot> LiveModel::snapshot() const {
  std::lock_guard lock(mutex_);
  return snapshot_;
}

PatchCache::Pin LiveModel::positions(const ModelSnapshot& snapshot, const PatchKey& key) {
  const PatchInfo& info = snapshot.model->at(key);
  return store_->cache().get(store_->id(), {key, info.version, MemoryCategory::Positions});
}

PatchCache::Pin LiveModel::texture(const ModelSnapshot& snapshot, const PatchKey& key) {
  const PatchInfo& info = snapshot.model->at(key);
  if (info.textureFile().empty()) {
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

void LiveModel::chargeMetadata() {
  std::vector<std::shared_ptr<const ModelSnapshot>> snapshots;  // let go after the lock
  {
    std::lock_guard lock(mutex_);
    snapshots.push_back(snapshot_);
    for (const auto& [number, weak] : revisionSnapshots_) {
      if (std::shared_ptr<ModelSnapshot> revision = weak.lock()) {
        snapshots.push_back(std::move(revision));
      }
    }
  }
  std::vector<std::shared_ptr<const Model>> held;
  for (const std::shared_ptr<const ModelSnapshot>& snapshot : snapshots) {
    held.push_back(snapshot->model);
  }
  for (const IndexBaseMemo* memo : {indexBases_.get(), revisionBases_.get()}) {
    if (memo != nullptr) {
      if (std::shared_ptr<const Model> base = memo->model()) {
        held.push_back(std::move(base));
      }
    }
  }
  std::unordered_set<const void*> counted;
  std::size_t bytes = store_->otherVersionsBytes();
  for (const std::shared_ptr<const Model>& model : held) {
    bytes += model->heapBytes(counted);
  }
  if (writer_ != nullptr) {
    bytes += writer_->hierarchyText.bytes();
  }
  store_->cache().chargeMetadata(store_->id(), bytes);
}

void LiveModel::removeLeftovers() {
  if (writer_ == nullptr) {
    return;
  }
  std::lock_guard lock(writer_->leftoversMutex);
  if (!writer_->leftoversRemoved) {
    std::map<std::uint64_t, fs::path> kept = sweepLeftovers(dir_, name_, *snapshot());
    writer_->leftoversRemoved = true;
    // No publish can have come between (beginEdit sweeps first): the list dropRevisions keeps.
    std::lock_guard writerLock(writer_->mutex);
    if (!writer_->revisionFiles) {
      writer_->revisionFiles = std::move(kept);
    }
  }
}

std::unique_ptr<ModelEdit> LiveModel::beginEdit() {
  if (writer_ == nullptr) {
    throw Error(ErrorCode::Conflict,
                "model '" + name_ + "' is open for reading only" +
                    (readOnlyReason_.empty() ? std::string() : ": " + readOnlyReason_));
  }
  removeLeftovers();  // before any draft of this process exists
  const std::optional<HierarchyStamp> onDisk = hierarchyStamp(dir_);  // no lock held over I/O
  std::lock_guard lock(writer_->mutex);
  if (writer_->editing) {
    throw Error(ErrorCode::Conflict, "model '" + name_ + "' is being changed by another job");
  }
  checkCurrent(onDisk);
  writer_->editing = true;
  try {
    return std::unique_ptr<ModelEdit>(new ModelEdit(*this, snapshot()));
  } catch (...) {
    writer_->editing = false;
    throw;
  }
}

void LiveModel::checkCurrent(const std::optional<HierarchyStamp>& onDisk) const {
  if (writer_->current != this) {
    throw Error(ErrorCode::Conflict, "model '" + name_ +
                                         "' was read again from disk since this opening was "
                                         "made; edits go through the new opening");
  }
  std::lock_guard lock(mutex_);
  if (onDisk != readStamp_) {
    throw Error(ErrorCode::Conflict,
                "the hierarchy of model '" + name_ +
                    "' on disk is not the one this process last read or published (version " +
                    std::to_string(snapshot_->version) +
                    "): another writer changed it; the model must be read again");
  }
}

}  // namespace vsm::core
