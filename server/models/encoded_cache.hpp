#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "core/cache/patch_cache.hpp"
#include "core/opc/stored_file.hpp"

namespace vsm::core {
class LiveModel;
}

namespace vsm::server::models {

/// The encodings of patch data the server caches as response bodies.
enum class Encoding : std::uint8_t {
  /// Positions as the full-grid .aara of a patch whose stored file is laid out otherwise (cropped,
  /// V3d), or whose file could not be held open.
  PositionsAara = 1,
  /// A 3D Tiles tile: binary glTF, float32 (`?compress=none`).
  Glb = 2,
  /// A texture tile as PNG.
  TexturePng = 3,
  /// A quantized-mesh terrain tile (server/api/terrain_routes.cpp), keyed not by a patch but by
  /// the terrain tile (z, x, y as a PatchKey) and, as its "version", a digest of the versions of
  /// the patches it was sampled from and of the representation (extensions, gzip). A publish
  /// does not drop these (dropVersion knows patches only): entries of replaced patches are no
  /// longer asked for and go as the policy evicts them.
  Terrain = 4,
  /// A 3D Tiles tile: binary glTF, KHR_mesh_quantization + EXT_meshopt_compression (the default).
  GlbMeshopt = 5,
  /// A model-wide JSON document, gzipped (findModelBody/putModelBody): tileset.json, the
  /// terrain's layer.json.
  JsonGzip = 6,
  /// Not a body: the working memory of a diff in progress (its map and picture, allocated outside
  /// the cache), charged while the diff runs (reserve()).
  DiffWork = 7,
  /// Not a body: the working memory of a height coverage being sampled and encoded (its strip
  /// buffers and the GeoTIFF), charged while it is made (reserve()).
  HeightWork = 8,
  /// A terrain-RGB tile as PNG (server/api/terrain_routes.cpp), keyed as Terrain's (the Web
  /// Mercator tile's z, x, y and a digest of its sources' versions and its encoding).
  TerrainRgb = 9,
  /// Not a body: the working memory of a ray query (server/api/ray_routes.cpp), one ray's
  /// hierarchy at a time, charged while it is built and cast (reserve()).
  RayWork = 10,
};

inline constexpr std::array<Encoding, 10> kEncodings{
    Encoding::PositionsAara, Encoding::Glb,      Encoding::TexturePng, Encoding::Terrain,
    Encoding::GlbMeshopt,    Encoding::JsonGzip, Encoding::DiffWork,   Encoding::HeightWork,
    Encoding::TerrainRgb,    Encoding::RayWork};
/// The name /v1/stats and the metrics give an encoding: "aara", "glb", "png", "terrain",
/// "glb_meshopt", "json_gzip", "diff", "heights", "terrain_rgb", "rays".
std::string_view toString(Encoding encoding);

/// The stored files of a patch the server sends as they are (sendfile(2)).
enum class StoredKind : std::uint8_t { Positions = 1, Coordinates = 2 };

/// Response material derived from one open model's published patches, kept in the shared
/// PatchCache under the model's name and charged to the one budget: encoded bodies
/// (MemoryCategory::Encoded, their bytes) and stored files held open for sendfile(2)
/// (MemoryCategory::OpenFiles: a few bytes each, and one descriptor against the cache's handle
/// budget, so that cached files never take the descriptors connections need). Entries are keyed
/// by patch key, patch version and kind, are clean (evicting one drops it) and go when a publish
/// replaces their version (the LiveModel's publish observer) or the model closes.
///
/// What find() and put() return holds the entry for the length of a response: pinned (charged,
/// never evicted) until the last copy goes, so the bytes of responses in flight count against the
/// budget. It also holds this cache (and so the model's cache registration) alive.
///
/// Thread-safe (the PatchCache is); find() never blocks, so network threads may call it.
class EncodedCache : public std::enable_shared_from_this<EncodedCache> {
 public:
  /// An encoded body held for a response.
  class Body;
  /// A stored file held open for a response.
  class File;

  /// A cache for `live`'s patches in `cache` (which must outlive it), dropping the entries of
  /// versions `live` publishes replacements for.
  static std::shared_ptr<EncodedCache> create(core::PatchCache& cache, core::LiveModel& live);
  /// Drops every entry. Precondition: nothing returned by find()/put() is alive (they hold this).
  ~EncodedCache();
  EncodedCache(const EncodedCache&) = delete;
  EncodedCache& operator=(const EncodedCache&) = delete;

  /// The cached body, or nullptr. `countMiss`: false for the handler pool's second look after a
  /// network thread's first one missed (one miss per request in the statistics).
  std::shared_ptr<const Body> find(const core::PatchKey& key, std::uint64_t version,
                                   Encoding encoding, bool countMiss) const;
  /// Caches `bytes` as the body, with `note` (a short text the encoder keeps beside them, such as
  /// a response header's value), evicting others to make room, and returns it held. Throws
  /// core::Error(ResourceExhausted) when the budget is full of pinned data.
  std::shared_ptr<const Body> put(const core::PatchKey& key, std::uint64_t version,
                                  Encoding encoding, std::vector<std::byte> bytes,
                                  std::string note = {});

  /// A body of the whole model rather than of one patch (Encoding::JsonGzip): `variant` (1..255)
  /// names what the body depends on besides the model's version (such as query parameters), and
  /// `version` is the snapshot's version. find as find(); put keeps one version per variant and
  /// encoding, dropping the one it replaces (publishes name patch versions only, so they cannot
  /// drop these). Stored under a key no patch has (depth -1, x = variant).
  std::shared_ptr<const Body> findModelBody(Encoding encoding, std::uint8_t variant,
                                            std::uint64_t version, bool countMiss) const;
  std::shared_ptr<const Body> putModelBody(Encoding encoding, std::uint8_t variant,
                                           std::uint64_t version, std::vector<std::byte> bytes);

  /// Charges `bytes` of working memory that a request allocates outside the cache (`encoding`,
  /// such as Encoding::DiffWork) to the budget until the returned hold is let go: a pinned entry
  /// no find() ever returns, made room for by evicting others like any put(). Throws
  /// core::Error(ResourceExhausted) when the budget is full of pinned data.
  std::shared_ptr<const void> reserve(Encoding encoding, std::size_t bytes);

  /// Counts one miss in the statistics (see core::PatchCache::countMiss).
  void countMiss() const;

  /// The cached open file, or nullptr (as find()).
  std::shared_ptr<const File> findFile(const core::PatchKey& key, std::uint64_t version,
                                       StoredKind kind, bool countMiss) const;
  /// Caches the open file, closing the least recently used unpinned ones beyond the handle
  /// budget, and returns it held. Throws core::Error(ResourceExhausted) when every file the
  /// budget allows is being sent (`file` is closed then).
  std::shared_ptr<const File> putFile(const core::PatchKey& key, std::uint64_t version,
                                      StoredKind kind, std::unique_ptr<core::StoredFile> file);

  /// Drops every entry of `key` at `version` (entries in use go when their last holder does).
  void dropVersion(const core::PatchKey& key, std::uint64_t version);

 private:
  explicit EncodedCache(core::PatchCache& cache);
  class Store;  // the PatchStore the cache needs; it never loads and never writes
  template <typename Held>
  std::shared_ptr<const Held> hold(core::PatchCache::Pin pin) const;

  core::PatchCache& cache_;
  std::unique_ptr<Store> store_;
  core::PatchCache::ModelId model_ = 0;
  /// Guards modelBodies_ only; never held while calling into cache_.
  std::mutex modelBodiesMutex_;
  /// (encoding, variant) -> the version putModelBody() last stored.
  std::map<std::pair<Encoding, std::uint8_t>, std::uint64_t> modelBodies_;
  /// Numbers reservations (guarded by modelBodiesMutex_).
  std::uint32_t reservations_ = 0;
};

/// What an Encoded entry holds.
struct EncodedBytes {
  std::vector<std::byte> bytes;
  std::string note;
};

class EncodedCache::Body {
 public:
  std::span<const std::byte> bytes() const { return encoded_->bytes; }
  std::string_view text() const {
    return {reinterpret_cast<const char*>(encoded_->bytes.data()), encoded_->bytes.size()};
  }
  const std::string& note() const { return encoded_->note; }

 private:
  friend class EncodedCache;
  std::shared_ptr<const EncodedCache> owner_;  // outlives pin_
  core::PatchCache::Pin pin_;
  const EncodedBytes* encoded_ = nullptr;
};

class EncodedCache::File {
 public:
  int fd() const { return file_->fd(); }
  std::size_t size() const { return file_->size(); }

 private:
  friend class EncodedCache;
  std::shared_ptr<const EncodedCache> owner_;  // outlives pin_
  core::PatchCache::Pin pin_;
  const core::StoredFile* file_ = nullptr;
};

}  // namespace vsm::server::models
