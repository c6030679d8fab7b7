#include "server/models/model_registry.hpp"

#include <algorithm>
#include <system_error>
#include <utility>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/store/live_model.hpp"
#include "core/store/model_edit.hpp"
#include "server/models/encoded_cache.hpp"

namespace vsm::server::models {

namespace fs = std::filesystem;
using core::Error;
using core::ErrorCode;
namespace log = core::log;

namespace {

bool isIdChar(char c) {
  return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' ||
         c == '-';
}

/// True when `path` lies strictly below `root` (both lexically normal and absolute).
bool isStrictlyInside(const fs::path& root, const fs::path& path) {
  auto r = root.begin();
  auto p = path.begin();
  for (; r != root.end(); ++r, ++p) {
    if (r->empty() && std::next(r) == root.end()) {
      break;  // a trailing separator of the root ("/data/") adds an empty last element
    }
    if (p == path.end() || *r != *p) {
      return false;
    }
  }
  for (; p != path.end(); ++p) {
    if (!p->empty()) {
      return true;
    }
  }
  return false;
}

}  // namespace

bool isValidModelId(std::string_view id) {
  return !id.empty() && id.size() <= 64 && std::all_of(id.begin(), id.end(), isIdChar);
}

void checkModelId(std::string_view id, std::string_view what) {
  if (!isValidModelId(id)) {
    // The id is not echoed verbatim: it may hold control characters or be very long.
    throw Error(ErrorCode::InvalidArgument,
                std::string(what) + " must be 1 to 64 characters of A-Z, a-z, 0-9, '_' and '-'");
  }
}

fs::path resolveInside(const fs::path& root, std::string_view relative) {
  const auto bad = [](std::string_view why) {
    throw Error(ErrorCode::InvalidArgument, "source path " + std::string(why));
  };
  if (relative.empty()) {
    bad("is empty");
  }
  if (relative.find('\0') != std::string_view::npos) {
    bad("contains a NUL byte");
  }
  const fs::path path(relative);
  if (path.is_absolute() || relative.front() == '/' || path.has_root_name()) {
    bad("must be relative to the data root");
  }
  for (const fs::path& part : path) {
    if (part == "..") {
      bad("must not contain '..'");
    }
  }
  std::error_code ec;
  // Resolves every symbolic link of the part that exists: a link out of the root is caught here.
  fs::path resolved = fs::weakly_canonical(root / path, ec);
  if (ec) {
    bad("cannot be resolved (" + ec.message() + ")");
  }
  if (!resolved.has_filename()) {
    resolved = resolved.parent_path();  // "a/b/" names the directory "a/b"
  }
  if (!isStrictlyInside(root, resolved)) {
    bad("leads outside the data root");
  }
  return resolved;
}

// ---- Lease -----------------------------------------------------------------------------------

ModelRegistry::Lease::Lease(Lease&& other) noexcept
    : registry_(std::exchange(other.registry_, nullptr)), id_(std::move(other.id_)) {}

ModelRegistry::Lease& ModelRegistry::Lease::operator=(Lease&& other) noexcept {
  if (this != &other) {
    release();
    registry_ = std::exchange(other.registry_, nullptr);
    id_ = std::move(other.id_);
  }
  return *this;
}

ModelRegistry::Lease::~Lease() {
  release();
}

void ModelRegistry::Lease::release() {
  if (registry_ != nullptr) {
    std::exchange(registry_, nullptr)->unlease(id_);
  }
}

// ---- ModelRegistry ---------------------------------------------------------------------------

ModelRegistry::ModelRegistry(const fs::path& dataRoot, core::PatchCache& cache,
                             std::uint64_t texturePixels, unsigned keepRevisions,
                             std::chrono::seconds keepSeconds)
    : root_(fs::canonical(dataRoot)),
      cache_(cache),
      texturePixels_(texturePixels),
      keepRevisions_(keepRevisions),
      keepSeconds_(keepSeconds) {}

ModelRegistry::~ModelRegistry() {
  std::map<std::string, Served, std::less<>> models;
  {
    const std::lock_guard lock(mutex_);
    models.swap(models_);
  }
  models.clear();  // outside the lock: closing writes dirty data back
}

void ModelRegistry::limitModels(std::size_t max) {
  const std::lock_guard lock(mutex_);
  maxModels_ = max;
}

bool ModelRegistry::atLimit() const {
  const std::lock_guard lock(mutex_);
  return models_.size() + opening_.size() + reserved_.size() >= maxModels_;
}

void ModelRegistry::checkRoomLocked(std::string_view id) const {
  if (models_.size() + opening_.size() + reserved_.size() >= maxModels_) {
    throw Error(ErrorCode::Conflict, "cannot open model '" + std::string(id) +
                                         "': vsmd serves at most " + std::to_string(maxModels_) +
                                         " models (limits.models); close one or raise the limit");
  }
}

std::size_t ModelRegistry::openAll() {
  std::vector<fs::path> dirs;
  std::error_code ec;
  for (fs::directory_iterator it(root_, ec), end; !ec && it != end; it.increment(ec)) {
    std::error_code typeError;
    if (it->is_directory(typeError)) {
      dirs.push_back(it->path());
    }
  }
  if (ec) {
    log::warn("cannot list the data root " + root_.string() + ": " + ec.message());
  }
  std::sort(dirs.begin(), dirs.end());
  std::size_t opened = 0;
  for (const fs::path& dir : dirs) {
    const std::string id = dir.filename().string();
    if (find(id) != nullptr) {
      continue;
    }
    // Skipped before and unchanged since: skipped again without a word.
    const std::optional<core::HierarchyStamp> stamp = core::hierarchyStamp(dir);
    if (const auto it = skipped_.find(id); it != skipped_.end() && it->second == stamp) {
      continue;
    }
    skipped_[id] = stamp;
    if (!isValidModelId(id)) {
      log::info("data root: skipping '" + id + "' (not a model id)");
      continue;
    }
    std::error_code linkError;
    const fs::path resolved = fs::canonical(dir, linkError);
    if (linkError || !isStrictlyInside(root_, resolved)) {
      log::warn("model=" + id + " skipped: the directory leads outside the data root");
      continue;
    }
    try {
      open(id, resolved);
      skipped_.erase(id);
      retrying_.erase(id);
      ++opened;
    } catch (const Error& e) {
      if (e.code() == ErrorCode::Io || e.code() == ErrorCode::Unavailable) {
        // Perhaps transient (a disk's read error, a file being replaced): tried again at the next
        // call, whatever the hierarchy's stamp, and said once until it opens.
        skipped_.erase(id);
        if (retrying_.insert(id).second) {
          log::warn("model=" + id + " not opened yet: " + e.what() + " (tried again)");
        }
      } else if (e.code() == ErrorCode::NotFound) {
        log::info("data root: skipping '" + id + "' (no OPC hierarchy)");
      } else if (e.code() != ErrorCode::Conflict || atLimit()) {
        // Conflict: opened or imported meanwhile, or no room left
        log::warn("model=" + id + " skipped: cannot open: " + e.what());
      }
    } catch (const std::exception& e) {
      log::warn("model=" + id + " skipped: cannot open: " + e.what());
    }
  }
  return opened;
}

void ModelRegistry::onPublished(std::function<void(const Publication&)> listener) {
  onPublished_ = std::move(listener);
}

void ModelRegistry::watch(core::LiveModel& live) const {
  if (!onPublished_) {
    return;
  }
  live.onNewVersion([listener = onPublished_, id = live.name()](
                        std::uint64_t version, const std::set<core::PatchKey>& changed,
                        const std::set<core::PatchKey>& removed) {
    Publication publication;
    publication.model = id;
    publication.version = version;
    publication.changed.assign(changed.begin(), changed.end());
    publication.removed.assign(removed.begin(), removed.end());
    listener(publication);
  });
}

void ModelRegistry::electWriters(std::function<bool(std::string_view id)> writes) {
  writes_ = std::move(writes);
}

bool ModelRegistry::setWriter(std::string_view id, bool writer) {
  const std::shared_ptr<core::LiveModel> old = find(id);
  if (old == nullptr) {
    return false;
  }
  if (old->writable() == writer) {
    return true;
  }
  const std::string name(id);
  Served fresh;
  try {
    fresh.live = core::LiveModel::open(
        old->dir(), name, cache_,
        writer ? core::LiveModel::Access::Write : core::LiveModel::Access::Read, texturePixels_);
    fresh.encoded = EncodedCache::create(cache_, *fresh.live);
    watch(*fresh.live);
  } catch (const std::exception& e) {
    bool first = false;
    {
      const std::lock_guard lock(mutex_);
      first = roleFailed_.insert(name).second;
    }
    if (first) {
      log::warn("model=" + name + " cannot be opened for " + (writer ? "writing" : "reading") +
                " (tried again every second): " + e.what());
    }
    return false;
  }
  const std::uint64_t version = fresh.live->snapshot()->version;
  if (!swapOpening(id, old, std::move(fresh))) {
    return false;  // closed or replaced meanwhile; asked again
  }
  {
    const std::lock_guard lock(mutex_);
    roleFailed_.erase(name);
  }
  log::info("model=" + name + (writer ? " is written by this process now" : " is only read now") +
            " (version " + std::to_string(version) + ")");
  return true;
}

std::vector<std::string> ModelRegistry::ids() const {
  const std::lock_guard lock(mutex_);
  std::vector<std::string> out;
  out.reserve(models_.size());
  for (const auto& [id, served] : models_) {
    out.push_back(id);
  }
  return out;
}

std::shared_ptr<core::LiveModel> ModelRegistry::open(const std::string& id, const fs::path& dir) {
  return openChecked(id, dir, false);
}

std::shared_ptr<core::LiveModel> ModelRegistry::openReserved(const Lease& reservation,
                                                             const fs::path& dir) {
  if (reservation.registry_ != this) {
    throw Error(ErrorCode::Internal, "openReserved without a reservation");
  }
  return openChecked(reservation.id_, dir, true);
}

std::shared_ptr<core::LiveModel> ModelRegistry::openChecked(const std::string& id,
                                                            const fs::path& dir, bool reserved) {
  checkModelId(id);
  std::error_code ec;
  const fs::path canonical = fs::weakly_canonical(dir, ec);
  if (ec) {
    throw Error(ErrorCode::NotFound, "cannot resolve '" + dir.string() + "': " + ec.message());
  }
  {
    const std::lock_guard lock(mutex_);
    if (models_.contains(id) || opening_.contains(id)) {
      throw Error(ErrorCode::Conflict, "model '" + id + "' is open already");
    }
    if (reserved_.contains(id) && !reserved) {
      throw Error(ErrorCode::Conflict, "model '" + id + "' is being imported");
    }
    if (!reserved) {  // a reservation holds its place already
      checkRoomLocked(id);
    }
    for (const auto& [other, model] : models_) {
      if (model.live->dir() == canonical) {
        throw Error(ErrorCode::Conflict, "that directory is open already as model '" + other + "'");
      }
    }
    opening_.insert(id);
  }
  std::shared_ptr<core::LiveModel> model;
  std::shared_ptr<EncodedCache> encoded;
  try {
    const bool elected = !writes_ || writes_(id);
    model = core::LiveModel::open(
        canonical, id, cache_,
        elected ? core::LiveModel::Access::WriteIfPossible : core::LiveModel::Access::Read,
        texturePixels_);
    if (elected && !model->writable()) {
      log::warn("model=" + id + " opened for reading only: " + model->readOnlyReason());
    }
    encoded = EncodedCache::create(cache_, *model);
    watch(*model);
  } catch (...) {
    const std::lock_guard lock(mutex_);
    opening_.erase(id);
    throw;
  }
  {
    const std::lock_guard lock(mutex_);
    opening_.erase(id);
    reserved_.erase(id);
    takeovers_.saw(id, *model);
    models_.emplace(id, Served{model, std::move(encoded)});
  }
  const auto snapshot = model->snapshot();
  log::info("model=" + id + " opened " + canonical.string() + ": " +
            std::to_string(snapshot->model->patchCount()) + " patches, depth " +
            std::to_string(snapshot->model->maxDepth()));
  return model;
}

void ModelRegistry::fenceWrites(WriterFence fence) {
  fence_ = std::move(fence);
}

core::PublishOptions ModelRegistry::publishOptions(const std::string& id, std::string job) const {
  core::PublishOptions options;
  options.job = std::move(job);
  options.keepRevisions = keepRevisions_;
  options.keepSeconds = keepSeconds_;
  options.deferFolderRemoval = true;
  if (fence_.token) {
    options.token = fence_.token(id);
  }
  if (fence_.check) {
    options.fence = [check = fence_.check, id, token = options.token] { check(id, token); };
  }
  if (fence_.readElsewhere) {
    options.readElsewhere = [read = fence_.readElsewhere, id] { return read(id); };
  }
  return options;
}

namespace {

[[noreturn]] void throwNotOpen(std::string_view id) {
  throw Error(ErrorCode::NotFound, isValidModelId(id)
                                       ? "no open model '" + std::string(id) + "'"
                                       : std::string("no such model (not a valid model id)"));
}

}  // namespace

std::size_t ModelRegistry::housekeeping() {
  std::size_t removed = 0;
  for (const std::shared_ptr<core::LiveModel>& model : list()) {
    try {
      model->removeLeftovers();  // once per opening for writing, after the daemon is ready
    } catch (const std::exception& e) {
      log::warn("model=" + model->name() + " removing leftovers: " + e.what() +
                " (tried again in a moment)");
    }
    removed += model->removeRetiredFolders();
    model->chargeMetadata();
  }
  return removed;
}

std::shared_ptr<core::LiveModel> ModelRegistry::find(std::string_view id) const {
  const std::lock_guard lock(mutex_);
  const auto it = models_.find(id);
  return it == models_.end() ? nullptr : it->second.live;
}

std::shared_ptr<core::LiveModel> ModelRegistry::get(std::string_view id) const {
  auto model = find(id);
  if (model == nullptr) {
    throwNotOpen(id);
  }
  return model;
}

ModelRegistry::Served ModelRegistry::getServed(std::string_view id) const {
  {
    const std::lock_guard lock(mutex_);
    const auto it = models_.find(id);
    if (it != models_.end()) {
      return it->second;
    }
  }
  throwNotOpen(id);
}

std::vector<std::shared_ptr<core::LiveModel>> ModelRegistry::list() const {
  std::vector<std::shared_ptr<core::LiveModel>> out;
  const std::lock_guard lock(mutex_);
  out.reserve(models_.size());
  for (const auto& [id, model] : models_) {
    out.push_back(model.live);
  }
  return out;
}

std::size_t ModelRegistry::size() const {
  const std::lock_guard lock(mutex_);
  return models_.size();
}

void ModelRegistry::close(std::string_view id) {
  Served closed;
  {
    const std::lock_guard lock(mutex_);
    const auto it = models_.find(id);
    if (it == models_.end()) {
      throwNotOpen(id);
    }
    if (const auto lease = leases_.find(id); lease != leases_.end() && lease->second > 0) {
      throw Error(ErrorCode::Conflict,
                  "model '" + std::string(id) + "' is in use by a job; cancel the job first");
    }
    closed = std::move(it->second);
    models_.erase(it);
  }
  log::info("model=" + std::string(id) + " closed");
  // `closed` goes here, outside the lock; requests still holding the model keep it until they end.
}

ModelRegistry::Lease ModelRegistry::lease(std::string_view id) {
  const std::lock_guard lock(mutex_);
  if (!models_.contains(id)) {
    throwNotOpen(id);
  }
  ++leases_[std::string(id)];
  return Lease(this, std::string(id));
}

ModelRegistry::Lease ModelRegistry::reserve(const std::string& id) {
  checkModelId(id);
  const std::lock_guard lock(mutex_);
  if (models_.contains(id) || opening_.contains(id)) {
    throw Error(ErrorCode::Conflict, "model '" + id + "' is open already");
  }
  if (reserved_.contains(id)) {
    throw Error(ErrorCode::Conflict, "model '" + id + "' is being imported");
  }
  checkRoomLocked(id);
  reserved_.insert(id);
  ++leases_[id];
  return Lease(this, id);
}

void ModelRegistry::unlease(const std::string& id) {
  const std::lock_guard lock(mutex_);
  const auto it = leases_.find(id);
  if (it != leases_.end() && --it->second <= 0) {
    leases_.erase(it);
    reserved_.erase(id);
  }
}

}  // namespace vsm::server::models
