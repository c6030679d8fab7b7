#include "server/models/patch_data.hpp"

#include <array>
#include <charconv>
#include <chrono>
#include <cstring>
#include <exception>
#include <filesystem>
#include <future>
#include <map>
#include <mutex>
#include <optional>
#include <span>
#include <utility>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/stored_file.hpp"
#include "core/opc/texture_file.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "core/tiles/glb.hpp"
#include "core/tiles/quantized_mesh.hpp"
#include "core/tiles/terrain_footprints.hpp"
#include "core/tiles/terrain_rgb.hpp"
#include "core/tiles/tile_tree.hpp"
#include "server/http/gzip.hpp"

namespace vsm::server::models {

using core::Error;
using core::ErrorCode;

namespace {

/// The one rule of where a body is made (Asker): `find(countMiss)` looks in the budget (in one
/// place or several, counting at most one miss) and returns what it holds, empty (a null pointer,
/// nullopt) when missing; found, or on a network thread, that is the answer; on the pool `make()`
/// makes it and puts it there. The pool's look after a network thread's counts no second miss.
template <typename Find, typename Make>
auto lookOrMake(Asker asker, Find&& find, Make&& make) {
  auto held = find(asker != Asker::PoolAfterNetwork);
  if (held || asker == Asker::NetworkThread) {
    return held;
  }
  return decltype(held)(make());
}

/// lookOrMake for an encoded body: `make()` returns its bytes. Throws ResourceExhausted (503,
/// retry) when the budget is full of pinned data.
template <typename Make>
std::shared_ptr<const EncodedCache::Body> findOrMake(EncodedCache& encoded,
                                                     const core::PatchKey& key,
                                                     std::uint64_t version, Encoding encoding,
                                                     Asker asker, Make&& make) {
  return lookOrMake(
      asker, [&](bool countMiss) { return encoded.find(key, version, encoding, countMiss); },
      [&] { return encoded.put(key, version, encoding, make()); });
}

/// lookOrMake for a stored file held open: `open()` opens it. Throws ResourceExhausted (503,
/// retry) while every file the cache may hold is being sent.
template <typename Open>
std::shared_ptr<const EncodedCache::File> findOrOpen(EncodedCache& encoded,
                                                     const core::PatchKey& key,
                                                     std::uint64_t version, StoredKind kind,
                                                     Asker asker, Open&& open) {
  return lookOrMake(
      asker, [&](bool countMiss) { return encoded.findFile(key, version, kind, countMiss); },
      [&] { return encoded.putFile(key, version, kind, open()); });
}

std::vector<std::byte> bytesOf(std::string_view text) {
  const auto* bytes = reinterpret_cast<const std::byte*>(text.data());
  return {bytes, bytes + text.size()};
}

}  // namespace

std::string matrixText(const core::Mat4d& m) {
  std::string out;
  char text[32];
  for (std::size_t i = 0; i < m.m.size(); ++i) {
    const auto [end, ec] = std::to_chars(text, text + sizeof text, m.m[i]);
    out.append(i == 0 ? "" : ",");
    out.append(text, ec == std::errc() ? end : text);
  }
  return out;
}

// ---- retired bases ---------------------------------------------------------------------------

/// Bases replaced by a newer version's (a layer's or tile tree's, with the metadata they were made
/// from), released by releaseRetired() on the main thread's housekeeping: the last reference to a
/// version's Model map frees one node a patch (40% of a new tileset's time at 87k patches when a
/// request dropped it), which no request should wait for.
class Retired {
 public:
  void add(std::shared_ptr<const void> held) {
    const std::lock_guard lock(mutex_);
    held_.push_back(std::move(held));
  }
  void release() {
    std::vector<std::shared_ptr<const void>> releasing;
    {
      const std::lock_guard lock(mutex_);
      releasing.swap(held_);
    }
  }

 private:
  std::mutex mutex_;
  std::vector<std::shared_ptr<const void>> held_;
};

// ---- terrain layers --------------------------------------------------------------------------

/// The terrain layers of the published versions being served, built once per version: the first
/// request that needs a version's layer builds it, requests that need it meanwhile wait for that
/// build (on the CPU pool; network threads only look), and a failed build is forgotten so that the
/// next request tries again.
class TerrainLayers {
 public:
  explicit TerrainLayers(Retired& retired) : retired_(retired) {}

  using Layer = std::shared_ptr<const core::TerrainLayer>;

  /// The layer of `snapshot` when built already, else null. Never blocks (network threads).
  Layer find(const std::shared_ptr<const core::ModelSnapshot>& snapshot) const {
    std::shared_future<Layer> building;
    {
      const std::lock_guard lock(mutex_);
      const auto it = layers_.find(snapshot.get());
      if (it == layers_.end() || it->second.snapshot.lock() != snapshot) {
        return nullptr;
      }
      building = it->second.layer;
    }
    if (building.wait_for(std::chrono::seconds(0)) != std::future_status::ready) {
      return nullptr;
    }
    try {
      return building.get();
    } catch (...) {
      return nullptr;  // the request that built it reports the error
    }
  }

  /// The layer of `snapshot`, built (reading every patch of it through the cache) when missing,
  /// or waited for while another request builds it. Throws what the build throws.
  Layer get(core::LiveModel& live, const std::shared_ptr<const core::ModelSnapshot>& snapshot) {
    std::promise<Layer> promise;
    std::shared_future<Layer> building;
    {
      const std::lock_guard lock(mutex_);
      // Forget the layers of versions no longer served (their snapshots are gone).
      std::erase_if(layers_, [](const auto& entry) { return entry.second.snapshot.expired(); });
      auto& entry = layers_[snapshot.get()];
      if (entry.snapshot.lock() == snapshot) {
        building = entry.layer;
      } else {
        entry = {snapshot, promise.get_future().share()};
      }
    }
    if (building.valid()) {
      return building.get();  // no lock held while waiting
    }
    try {
      const auto start = std::chrono::steady_clock::now();
      // From the last layer built for the model in this directory: only what changed is read.
      std::optional<Base> base;
      {
        const std::lock_guard lock(mutex_);
        if (const auto it = bases_.find(live.dir()); it != bases_.end()) {
          base = it->second;
        }
      }
      std::optional<core::ModelChange> change;
      std::optional<core::TerrainLayerBase> previous;
      std::optional<core::SavedFootprints> saved;
      if (base) {
        change = core::changeSince(base->model, *snapshot);
        previous.emplace(core::TerrainLayerBase{*base->model, *base->layer, &*change});
      } else {
        saved = readSavedFootprints(live, *snapshot->model);
      }
      std::size_t read = 0;
      auto layer = std::make_shared<const core::TerrainLayer>(core::buildTerrainLayer(
          *snapshot->model,
          [&](const core::PatchInfo& info) {
            ++read;
            return live.positions(*snapshot, info.key).get<core::PatchGrid>();
          },
          previous ? &*previous : nullptr, saved ? &*saved : nullptr));
      saved.reset();
      {
        const std::lock_guard lock(mutex_);
        Base& held = bases_[live.dir()];
        retired_.add(std::move(held.model));
        retired_.add(std::move(held.layer));
        held = Base{snapshot->model, layer};
      }
      if (base) {
        retired_.add(std::move(base->model));  // this copy may be the last by now
      }
      core::log::info(
          "model=" + live.name() + " terrain layer of version " +
          std::to_string(snapshot->version) + ": " +
          (layer->heightField ? "levels 0.." + std::to_string(layer->maxZoom) : "no height field") +
          ", " +
          std::to_string(std::chrono::duration_cast<std::chrono::milliseconds>(
                             std::chrono::steady_clock::now() - start)
                             .count()) +
          " ms, read " + std::to_string(read) + " of " +
          std::to_string(snapshot->model->patchCount()) + " patches");
      promise.set_value(layer);
      if (!base) {
        saveFootprints(live, *snapshot->model, *layer, read);  // the requests waiting are served
      }
      return layer;
    } catch (...) {
      promise.set_exception(std::current_exception());
      const std::lock_guard lock(mutex_);
      if (const auto it = layers_.find(snapshot.get());
          it != layers_.end() && it->second.snapshot.lock() == snapshot) {
        layers_.erase(it);
      }
      throw;
    }
  }

 private:
  struct Entry {
    std::weak_ptr<const core::ModelSnapshot> snapshot;  // the key's owner, to detect reuse
    std::shared_future<Layer> layer;                    // ready once built
  };
  /// The footprints an earlier layer of the model saved (SavedFootprints): none when there is no
  /// such file, or a damaged one (a warning: the layer reads every patch, and saves afresh).
  static std::optional<core::SavedFootprints> readSavedFootprints(const core::LiveModel& live,
                                                                  const core::Model& model) {
    try {
      // A file for a version with up to twice as many patches is still of use.
      const std::size_t bound =
          64 + (2 * model.patchCount() + 1024) * core::SavedFootprints::kRecordBytes;
      if (auto bytes = live.readCacheFile(core::kSavedFootprintsFile, bound)) {
        return core::SavedFootprints(std::move(*bytes), model.gridSize());
      }
    } catch (const core::Error& e) {
      core::log::warn("model=" + live.name() + " " + e.what() + ": terrain footprints are read");
    }
    return std::nullopt;
  }

  /// Saves the layer's footprints when this layer, the first of the process, read more than an
  /// eighth of the model (a model without saved footprints, or saved long ago): later processes
  /// then read only what changed since. The writer's alone; a failure is a warning (a cache).
  static void saveFootprints(core::LiveModel& live, const core::Model& model,
                             const core::TerrainLayer& layer, std::size_t read) {
    if (!live.writable() || !layer.heightField || read * 8 <= model.patchCount()) {
      return;
    }
    try {
      live.writeCacheFile(core::kSavedFootprintsFile, core::SavedFootprints::encode(model, layer));
    } catch (const std::exception& e) {  // the layer is served: nothing to fail
      core::log::warn("model=" + live.name() + " terrain footprints not saved: " + e.what());
    }
  }

  /// The last layer built for a model (by its directory) and the metadata it was built from:
  /// the base of the next version's layer (kept beyond its snapshot; the metadata shares every
  /// unchanged patch with the newer versions', so it costs about its changed patches).
  struct Base {
    std::shared_ptr<const core::Model> model;
    Layer layer;
  };
  Retired& retired_;
  mutable std::mutex mutex_;  // guards layers_ and bases_ (layers are immutable once built)
  std::map<const core::ModelSnapshot*, Entry> layers_;
  std::map<std::filesystem::path, Base> bases_;
};

// ---- tile trees --------------------------------------------------------------------------------

/// The last root tile tree made per model (by directory) and levels, with the metadata it was made
/// from: the base of the next version's (kept beyond its snapshot; the metadata shares every
/// unchanged patch with the newer versions', so it costs about its changed patches).
class TileTrees {
 public:
  using Tree = std::shared_ptr<const core::TileNode>;

  explicit TileTrees(Retired& retired) : retired_(retired) {}

  Tree get(const std::filesystem::path& dir, const core::ModelSnapshot& snapshot, int levels) {
    const std::shared_ptr<const core::Model>& model = snapshot.model;
    std::optional<Last> last;
    {
      const std::lock_guard lock(mutex_);
      if (const auto it = last_.find({dir, levels}); it != last_.end()) {
        last = it->second;
      }
    }
    if (last && last->model == model) {
      return last->tree;
    }
    Tree tree;
    if (last) {
      const core::ModelChange change = core::changeSince(last->model, snapshot);
      const core::TileTreeBase base{*last->tree, change};
      tree = std::make_shared<const core::TileNode>(
          core::buildTileTree(*model, core::PatchKey::root(), levels, &base));
    } else {
      tree = std::make_shared<const core::TileNode>(
          core::buildTileTree(*model, core::PatchKey::root(), levels));
    }
    if (last) {
      retired_.add(std::move(last->model));
    }
    const std::lock_guard lock(mutex_);
    Last& held = last_[{dir, levels}];
    retired_.add(std::move(held.model));
    held = Last{model, tree};
    return tree;
  }

 private:
  struct Last {
    std::shared_ptr<const core::Model> model;
    Tree tree;
  };
  Retired& retired_;
  std::mutex mutex_;
  std::map<std::pair<std::filesystem::path, int>, Last> last_;
};

// ---- the service -----------------------------------------------------------------------------

PatchData::PatchData()
    : retired_(std::make_unique<Retired>()),
      layers_(std::make_unique<TerrainLayers>(*retired_)),
      trees_(std::make_unique<TileTrees>(*retired_)) {}

void PatchData::releaseRetired() {
  retired_->release();
}

PatchData::~PatchData() = default;

namespace {

/// The full-grid .aara of a patch whose stored file is laid out otherwise, with the Local2Global
/// it is based on: a cropped V3f file's rows are copied into place (no decoding); a V3d file is
/// decoded and re-based.
std::pair<std::vector<std::byte>, std::string> encodePositions(const core::LiveModel& live,
                                                               const core::ModelSnapshot& snapshot,
                                                               const core::PatchInfo& info) {
  if (std::optional<std::vector<std::byte>> bytes =
          core::readFullGridPositions(live.dir(), snapshot.model->gridSize(), info)) {
    return {std::move(*bytes), matrixText(info.local2global())};
  }
  const core::PatchGrid grid = core::readPatchGrid(live.dir(), *snapshot.model, info);
  const std::span<const float> floats = grid.positions();
  const std::int32_t n = grid.size();
  const std::array<std::int32_t, 2> sizes{n, n};
  std::vector<std::byte> bytes = core::encodeAaraHeader(core::AaraType::V3f, sizes);
  const std::size_t header = bytes.size();
  bytes.resize(header + floats.size_bytes());
  std::memcpy(bytes.data() + header, floats.data(), floats.size_bytes());
  return {std::move(bytes), matrixText(grid.local2global())};
}

}  // namespace

std::optional<PatchData::Positions> PatchData::positions(const ModelRegistry::Served& served,
                                                         const core::ModelSnapshot& snapshot,
                                                         const core::PatchInfo& info,
                                                         Asker asker) const {
  EncodedCache& encoded = *served.encoded;
  const core::PatchKey& key = info.key;
  const int n = snapshot.model->gridSize();
  const bool asStored = info.stored == core::GridRect{0, 0, n, n};
  // A patch stored whole is cached as its open file, or as a body when the file cannot be sent as
  // it is (V3d): one look for either, one miss counted when neither is there.
  const auto find = [&](bool countMiss) -> std::optional<Positions> {
    Positions held;
    if (asStored) {
      held.file = encoded.findFile(key, info.version, StoredKind::Positions, false);
    }
    if (held.file == nullptr) {
      held.body = encoded.find(key, info.version, Encoding::PositionsAara, false);
    }
    if (held.file == nullptr && held.body == nullptr) {
      if (countMiss) {
        encoded.countMiss();
      }
      return std::nullopt;
    }
    return held;
  };
  const auto make = [&] {
    Positions made;
    if (asStored) {
      if (std::unique_ptr<core::StoredFile> stored =
              core::openFullGridPositions(served.live->dir(), n, info)) {
        try {
          made.file = encoded.putFile(key, info.version, StoredKind::Positions, std::move(stored));
        } catch (const Error& e) {
          if (e.code() != ErrorCode::ResourceExhausted) {
            throw;
          }
          // Every descriptor the cache may hold is being sent: encode this one in the budget.
        }
      }
    }
    if (made.file == nullptr) {
      auto [bytes, local2global] = encodePositions(*served.live, snapshot, info);
      made.body = encoded.put(key, info.version, Encoding::PositionsAara, std::move(bytes),
                              std::move(local2global));
    }
    return made;
  };
  std::optional<Positions> out = lookOrMake(asker, find, make);
  if (out) {
    out->local2global =
        out->file != nullptr ? matrixText(info.local2global()) : std::string(out->body->note());
  }
  return out;
}

std::shared_ptr<const EncodedCache::File> PatchData::coordinates(
    const ModelRegistry::Served& served, const core::PatchInfo& info, Asker asker) const {
  return findOrOpen(*served.encoded, info.key, info.version, StoredKind::Coordinates, asker,
                    [&] { return core::openCoordinatesFile(served.live->dir(), info); });
}

std::shared_ptr<const EncodedCache::Body> PatchData::texturePng(const ModelRegistry::Served& served,
                                                                const core::PatchInfo& info,
                                                                Asker asker) const {
  return findOrMake(*served.encoded, info.key, info.version, Encoding::TexturePng, asker, [&] {
    return core::readPatchTexturePng(served.live->dir(), info, served.live->texturePixels());
  });
}

std::shared_ptr<const EncodedCache::Body> PatchData::glb(const ModelRegistry::Served& served,
                                                         const core::ModelSnapshot& snapshot,
                                                         const core::PatchInfo& info,
                                                         core::GlbCompression compression,
                                                         Asker asker) const {
  const Encoding encoding =
      compression == core::GlbCompression::Meshopt ? Encoding::GlbMeshopt : Encoding::Glb;
  return findOrMake(*served.encoded, info.key, info.version, encoding, asker, [&] {
    // A cache miss reads the disk here, and the encoding is CPU work. The pin is released before
    // the snapshot.
    const core::PatchCache::Pin pin = served.live->positions(snapshot, info.key);
    // The patch's texture tile (as JPEG, or PNG where it has transparent texels) and
    // coordinates, read from disk.
    const std::optional<core::PatchTexture> texture = core::readPatchTexture(
        served.live->dir(), *snapshot.model, info, served.live->texturePixels());
    core::GlbOptions options;
    options.compression = compression;
    if (texture) {
      options.texture = {texture->image, texture->mimeType};
      options.texcoords = texture->texcoords;
      options.baseColor = {1.0, 1.0, 1.0, 1.0};  // the texture's own colours
    }
    return core::encodeGlb(*pin.get<core::PatchGrid>(), core::tileCentre(info), options);
  });
}

std::shared_ptr<const core::TerrainLayer> PatchData::terrainLayer(
    const ModelRegistry::Served& served, const std::shared_ptr<const core::ModelSnapshot>& snapshot,
    Asker asker) {
  return asker == Asker::NetworkThread ? layers_->find(snapshot)
                                       : layers_->get(*served.live, snapshot);
}

std::shared_ptr<const core::TileNode> PatchData::rootTileTree(const ModelRegistry::Served& served,
                                                              const core::ModelSnapshot& snapshot,
                                                              int levels) const {
  return trees_->get(served.live->dir(), snapshot, levels);
}

std::function<std::shared_ptr<const core::PatchGrid>(const core::PatchInfo&)> PatchData::gridLoader(
    const ModelRegistry::Served& served, const core::ModelSnapshot& snapshot) const {
  return [&served, &snapshot](const core::PatchInfo& info) {
    return served.live->positions(snapshot, info.key).get<core::PatchGrid>();
  };
}

std::shared_ptr<const EncodedCache::Body> PatchData::terrainTile(
    const ModelRegistry::Served& served, const core::ModelSnapshot& snapshot,
    const TerrainTile& tile, Asker asker) const {
  const core::TerrainTileKey& key = *tile.key;
  // Cached under the tile as a key (z, x, y fit a PatchKey's fields) and its content version.
  const core::PatchKey cacheKey{key.z, key.x, key.y};
  return findOrMake(*served.encoded, cacheKey, tile.version, Encoding::Terrain, asker, [&] {
    const core::TerrainHeights heights =
        core::sampleTerrain(*snapshot.model, *tile.sources, key, gridLoader(served, snapshot));
    core::QuantizedMeshOptions options;
    options.normals = tile.normals;
    options.metadata = tile.metadata;
    std::vector<std::byte> bytes = core::encodeQuantizedMesh(heights, options);
    if (tile.gzipped) {
      bytes = bytesOf(
          http::gzip(std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size())));
    }
    return bytes;
  });
}

std::shared_ptr<const EncodedCache::Body> PatchData::demTile(const ModelRegistry::Served& served,
                                                             const core::ModelSnapshot& snapshot,
                                                             const DemTile& tile,
                                                             Asker asker) const {
  const core::MercatorTileKey& key = *tile.key;
  const core::PatchKey cacheKey{key.z, key.x, key.y};
  return findOrMake(*served.encoded, cacheKey, tile.version, Encoding::TerrainRgb, asker, [&] {
    const core::DemTile sampled =
        core::sampleDemTile(*snapshot.model, *tile.sources, key, gridLoader(served, snapshot),
                            tile.encoding, tile.nodataHeight);
    // Fast: at OpenImageIO's default the encoding took 70 % of a cold tile's time (perf), and
    // Fast answers 2.2x sooner for files 23 % larger (tests/bench/results/terrain-rgb.txt).
    return core::encodePng(sampled.rgb.data(), core::kDemTileSize, core::kDemTileSize, 3, {},
                           core::PngCompression::Fast);
  });
}

std::shared_ptr<const EncodedCache::Body> PatchData::gzippedJson(
    const ModelRegistry::Served& served, std::uint8_t variant, std::uint64_t version,
    const std::function<std::string()>& build) const {
  EncodedCache& encoded = *served.encoded;
  auto body = encoded.findModelBody(Encoding::JsonGzip, variant, version, true);
  if (body == nullptr) {
    body = encoded.putModelBody(Encoding::JsonGzip, variant, version, bytesOf(http::gzip(build())));
  }
  return body;
}

}  // namespace vsm::server::models
