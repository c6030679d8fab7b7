#include "core/store/model_edit.hpp"

#include <algorithm>
#include <array>
#include <optional>
#include <utility>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/common/random.hpp"
#include "core/grid/shaded_relief.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/texture_file.hpp"
#include "core/pyramid/reduce.hpp"
#include "core/store/model_store.hpp"
#include "core/store/store_files.hpp"

namespace fs = std::filesystem;

namespace vsm::core {

using namespace store;

namespace {

/// Deepest first, keeping the order within a depth: children before their parents.
void sortDeepestFirst(std::vector<PatchKey>& keys) {
  std::stable_sort(keys.begin(), keys.end(),
                   [](const PatchKey& a, const PatchKey& b) { return a.depth > b.depth; });
}

}  // namespace

ModelEdit::ModelEdit(LiveModel& live, std::shared_ptr<const ModelSnapshot> base)
    : live_(live),
      sync_(live.dir_),
      base_(std::move(base)),
      model_(std::make_shared<Model>(*base_->model)),
      nonce_(randomHex()) {}

ModelEdit::~ModelEdit() {
  if (!published_) {
    // Discard: the drafts leave the cache unwritten and their folders (if evicted) go.
    LiveModel::Store& store = *live_.store_;
    for (const PatchKey& key : changed_) {
      const ObjectId id = draftId(key);
      try {
        store.cache().drop(store.id(), id);
        store.cache().drop(store.id(), {key, id.version, MemoryCategory::Textures});
        const std::string folder = draftFolder(key, id.version, nonce_);
        fs::remove_all(patchesDirOf(live_.dir_) / folder);
        fs::remove(ourTileFile(live_.dir_, folder));
      } catch (const std::exception& e) {
        log::warn("model=" + live_.name_ + " discarding " + key.toString() + ": " + e.what());
      }
      store.forget(key, id.version);
    }
  }
  std::lock_guard lock(live_.writer_->mutex);
  live_.writer_->editing = false;
}

void ModelEdit::requireOpen() const {
  if (published_) {
    throw Error(ErrorCode::Conflict, "edit already published");
  }
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
  if (info.textureFile().empty()) {
    return {};
  }
  return live_.store_->cache().get(live_.store_->id(),
                                   {key, info.version, MemoryCategory::Textures});
}

void ModelEdit::setPositions(const PatchKey& key, std::shared_ptr<const PatchGrid> grid,
                             std::shared_ptr<const TextureTile> texture) {
  requireOpen();
  if (grid->size() != model_->gridSize()) {
    throw Error(ErrorCode::InvalidArgument, "patch " + key.toString() + " has a grid of " +
                                                std::to_string(grid->size()) + " instead of " +
                                                std::to_string(model_->gridSize()));
  }
  if (texture && texelsPerQuadOf(texture->size(), model_->gridSize()) == 0) {
    throw Error(ErrorCode::InvalidArgument,
                "patch " + key.toString() + " has a texture tile of " +
                    std::to_string(texture->size()) + " texels, not a power of two times " +
                    std::to_string(textureTileSize(model_->gridSize())));
  }
  if (model_->find(key) == nullptr) {
    PatchInfo info;
    info.key = key;
    info.hidden = hiddenForNew(key);
    model_->insert(std::move(info));
  }
  const ObjectId id = draftId(key);
  const ObjectId textureId{key, id.version, MemoryCategory::Textures};
  PatchInfo& info = model_->edit(key);
  LiveModel::Store& store = *live_.store_;
  if (!texture && changed_.count(key) != 0 && !info.textureFile().empty()) {
    // This edit's earlier texture of the patch is obsolete (and may have been written already).
    store.cache().drop(store.id(), textureId);
    fs::remove(ourTileFile(live_.dir_, info.folder()));
  }
  info.version = id.version;
  info.setFolder(draftFolder(key, id.version, nonce_));
  // As OpcWriter::writePatch names them: the snapshot (and the index written from it) says what
  // the files say.
  info.setFiles(
      texture ? PatchFiles{"Positions.aara", "Coordinates.aara", textureEntryFor(info.folder())}
              : PatchFiles{});
  model_->describe(key, *grid);
  model_->markChanged(key);
  if (const auto parent = key.parent()) {
    staleParents_.insert(*parent);
  }
  info.dirty = false;  // the cache tracks dirtiness; the model only needs `changed_`
  changed_.insert(key);
  store.add(model_->at(key));
  const std::size_t bytes = grid->bytes();
  store.cache().put(store.id(), id, {std::move(grid), bytes}, true);
  if (texture) {
    const std::size_t textureBytes = texture->bytes();
    store.cache().put(store.id(), textureId, {std::move(texture), textureBytes}, true);
  }
}

bool ModelEdit::hiddenForNew(const PatchKey& key) {
  // Hidden levels stay where they are (thesis 5.2, Figure 5.2): below a hidden patch, and beside
  // hidden siblings, a new patch is hidden; under a visible leaf, it is hidden in a model that has
  // hidden levels (the detail joins them, and what other readers see keeps its leaves).
  const std::optional<PatchKey> parent = key.parent();
  if (!parent) {
    return false;
  }
  const PatchInfo& up = model_->at(*parent);
  if (up.hidden) {
    return true;
  }
  for (const Quadrant q : kQuadrants) {
    if (const PatchInfo* sibling = model_->find(parent->child(q))) {
      return sibling->hidden;
    }
  }
  return visibleTexelsPerQuad() != 0;
}

int ModelEdit::visibleTexelsPerQuad() {
  if (!visibleTexelsPerQuad_) {
    // The texels per quad of the visible leaves, the patches whose children are hidden: what an
    // import with hidden levels gave them (--visible-texels-per-quad), read off one of their tiles.
    visibleTexelsPerQuad_ = 0;
    if (base_->model->hasHiddenLevels()) {
      for (const auto& [key, info] : base_->model->patches()) {
        if (info.hidden || !base_->model->childrenHidden(key)) {
          continue;
        }
        if (const PatchCache::Pin pin = live_.texture(*base_, key)) {
          visibleTexelsPerQuad_ =
              texelsPerQuadOf(pin.get<TextureTile>()->size(), model_->gridSize());
        }
        break;
      }
    }
  }
  return *visibleTexelsPerQuad_;
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
  requireOpen();
  // The stale patches are the ancestors of the patches given data (those a restore removed since
  // are gone, their ancestors stay stale): a walk up from each, not a look at 10^6 patches.
  std::set<PatchKey> candidates;
  for (const PatchKey& first : staleParents_) {
    for (std::optional<PatchKey> key = first; key && candidates.insert(*key).second;
         key = key->parent()) {
    }
  }
  std::vector<PatchKey> stale;
  for (const PatchKey& key : candidates) {
    if (const PatchInfo* info = model_->find(key); info != nullptr && info->stale) {
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
    // A child without a tile in vsm's layout (none, or a foreign one of another size) counts
    // with its shaded relief, computed while its grid is held anyway.
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
          if (info->textureFile().empty()) {
            reliefs[static_cast<int>(q)].emplace(shadedRelief(*children[static_cast<int>(q)]));
          }
        }
      }
      parent = std::make_shared<const PatchGrid>(reduce(children));
    }
    {
      // The parent's tile from its children's, one at a time as the grids, with as many texels
      // per quad as the finest of them (a coarser child's tile is upsampled to it), at most
      // kMaxTextureTileSize texels a side.
      const int gridSize = model_->gridSize();
      int size = textureTileSize(gridSize);
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
          const TextureTile* tile = pins[i].get<TextureTile>().get();
          if (texelsPerQuadOf(tile->size(), gridSize) != 0) {
            children[i] = tile;
            size = std::max(size, tile->size());
            continue;
          }
          pins[i] = {};
          const PatchCache::Pin grid = positions(child);
          reliefs[i].emplace(shadedRelief(*grid.get<PatchGrid>()));
        }
        children[i] = &*reliefs[i];
      }
      // A finer foreign tile is brought down to the largest tile vsm makes.
      size = std::min(size, textureTileSize(gridSize, maxTexelsPerQuad(gridSize)));
      std::array<std::optional<TextureTile>, 4> resized;
      for (int i = 0; i < 4; ++i) {
        if (children[i] != nullptr && children[i]->size() != size) {
          children[i] = &resized[i].emplace(resizeTile(*children[i], size));
        }
      }
      // Above a hidden level, twice the children's texels per quad (their tiles side by side, as
      // the import made them) up to the visible leaves' (core/opc/README.md, "Hidden levels").
      const int visible = visibleTexelsPerQuad();
      const bool sideBySide = visible != 0 && model_->childrenHidden(key) &&
                              2 * texelsPerQuadOf(size, gridSize) <= visible;
      TextureTile tile(sideBySide ? 2 * size : size);
      for (int i = 0; i < 4; ++i) {
        if (children[i] != nullptr) {
          downsampleQuadrant(*children[i], i, tile);
        }
      }
      parentTexture = std::make_shared<const TextureTile>(std::move(tile));
    }
    setPositions(key, std::move(parent), std::move(parentTexture));
    model_->edit(key).stale = false;
  }
}

void ModelEdit::restore(const ModelSnapshot& from, const CancelToken* cancel) {
  requireOpen();
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
  // Every overview is `from`'s own now: none is recomputed. Hidden levels are `from`'s too.
  for (const auto& [key, info] : target.patches()) {
    PatchInfo& edited = model_->edit(key);
    edited.stale = false;
    edited.hidden = info.hidden;
  }
}

}  // namespace vsm::core
