#include "server/api/etags.hpp"

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <type_traits>

#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "server/http/message.hpp"

namespace vsm::server::api {

namespace {

/// FNV-1a, 64 bits: a digest for entity tags (not a security boundary: the server makes them).
class Digest {
 public:
  void add(const void* data, std::size_t size) {
    const auto* bytes = static_cast<const unsigned char*>(data);
    for (std::size_t i = 0; i < size; ++i) {
      hash_ = (hash_ ^ bytes[i]) * 1099511628211ull;
    }
  }
  template <typename T>
  void add(const T& value) {
    static_assert(std::is_trivially_copyable_v<T>);
    add(&value, sizeof value);
  }
  void add(std::string_view text) {
    add(text.size());
    add(text.data(), text.size());
  }
  void add(const core::Box3d& box) {
    for (const double v : {box.min.x, box.min.y, box.min.z, box.max.x, box.max.y, box.max.z}) {
      add(v);
    }
  }
  std::uint64_t value() const { return hash_; }
  std::string hex() const {
    char text[17];
    std::snprintf(text, sizeof text, "%016llx", static_cast<unsigned long long>(hash_));
    return text;
  }

 private:
  std::uint64_t hash_ = 14695981039346656037ull;
};

/// The model's digest as a tag's start: core::modelDigest, which the snapshot keeps (made once
/// when a version is read, then by the change at each publish), so no request walks the model.
Digest modelDigest(const core::ModelSnapshot& snapshot) {
  Digest digest;
  digest.add(snapshot.digest);
  return digest;
}

}  // namespace

std::string modelEtag(const core::ModelSnapshot& snapshot) {
  return http::strongEtag("m" + modelDigest(snapshot).hex());
}

std::string viewEtag(const core::ModelSnapshot& snapshot, std::string_view view,
                     std::string_view query) {
  Digest digest = modelDigest(snapshot);
  digest.add(view);
  digest.add(query);
  return http::strongEtag(std::string(view) + digest.hex());
}

std::string patchEtag(const core::PatchInfo& info) {
  Digest digest;
  digest.add(core::patchDigest(info));
  return http::strongEtag(info.key.toString() + "-v" + std::to_string(info.version) + "-" +
                          digest.hex().substr(0, 8));
}

std::string patchDataEtag(const core::PatchInfo& info, std::string_view suffix) {
  return http::strongEtag(std::string(http::opaqueOf(patchEtag(info))) + "-" + std::string(suffix));
}

std::string tilesetEtag(const core::ModelSnapshot& snapshot, std::string_view variant) {
  return http::strongEtag("tileset-" + std::string(http::opaqueOf(modelEtag(snapshot))) + "-" +
                          std::string(kTilesFormat) + (variant.empty() ? "" : "-") +
                          std::string(variant));
}

std::string staticFileEtag(std::uint64_t size, std::uint64_t mtimeNs, std::uint64_t inode) {
  const auto hex = [](std::uint64_t value) {
    char text[17];
    std::snprintf(text, sizeof text, "%llx", static_cast<unsigned long long>(value));
    return std::string(text);
  };
  return http::strongEtag("s-" + hex(size) + "-" + hex(mtimeNs) + "-" + hex(inode));
}

std::uint64_t terrainVersion(std::string_view tile, const core::Model& model,
                             std::span<const core::PatchKey> sources, std::string_view variant) {
  Digest digest;
  digest.add(kTerrainFormat);
  digest.add(tile);
  digest.add(variant);
  for (const core::PatchKey& key : sources) {
    digest.add(key.depth);
    digest.add(key.x);
    digest.add(key.y);
    digest.add(model.at(key).version);
  }
  return digest.value();
}

std::string terrainEtag(std::string_view tile, std::uint64_t version) {
  char text[17];
  std::snprintf(text, sizeof text, "%016llx", static_cast<unsigned long long>(version));
  std::string name(tile);
  std::replace(name.begin(), name.end(), '/', '_');
  return http::strongEtag("terrain-" + name + "-" + text);
}

std::string glbEtag(const core::PatchInfo& info, std::string_view variant) {
  return patchDataEtag(info, "glb-" + std::string(kTilesFormat) + (variant.empty() ? "" : "-") +
                                 std::string(variant));
}

}  // namespace vsm::server::api
