#include "server/api/etags.hpp"

#include <algorithm>
#include <array>
#include <cstdint>
#include <cstdio>
#include <memory>
#include <mutex>
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

void addPatch(Digest& digest, const core::PatchInfo& info) {
  digest.add(info.key.depth);
  digest.add(info.key.x);
  digest.add(info.key.y);
  digest.add(info.version);
  digest.add(std::string_view(info.folder));
  digest.add(info.childMask);
  digest.add(info.globalBox);
  digest.add(info.local2global.m);
}

/// The digests of the last models asked about: a model's takes a pass over every patch (about
/// 40 ms at 87k patches), and every request for the model's metadata or tileset asks for it. A
/// published model never changes, so its digest is made once; the entries hold the models weakly
/// (an entry whose model is gone is remade, even if a new model has its address).
class ModelDigests {
 public:
  Digest of(const std::shared_ptr<const core::Model>& model) {
    {
      const std::lock_guard lock(mutex_);
      for (const Entry& entry : entries_) {
        if (entry.model.lock() == model) {
          return entry.digest;
        }
      }
    }
    Digest digest;  // made without the lock: concurrent first requests may both make it
    digest.add(model->gridSize());
    for (const auto& [key, info] : model->patches()) {
      addPatch(digest, info);
    }
    const std::lock_guard lock(mutex_);
    entries_[next_] = {model, digest};
    next_ = (next_ + 1) % entries_.size();
    return digest;
  }

 private:
  struct Entry {
    std::weak_ptr<const core::Model> model;
    Digest digest;
  };
  std::mutex mutex_;
  /// The models of a few versions of a few models (several models open, kept revisions read).
  std::array<Entry, 16> entries_;
  std::size_t next_ = 0;
};

Digest modelDigest(const core::ModelSnapshot& snapshot) {
  static ModelDigests digests;
  return digests.of(snapshot.model);
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
  addPatch(digest, info);
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
