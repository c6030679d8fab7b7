#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string_view>
#include <vector>

#include "core/tiles/quantized_mesh.hpp"

namespace vsm::core {

class Model;
struct PatchInfo;

/// The file beside a model's hierarchy (in Patches/) that holds its saved footprints: a cache, vsm
/// rebuilds what it lacks; other OPC tools ignore it.
inline constexpr std::string_view kSavedFootprintsFile = "vsm-terrain-footprints.bin";

/// The footprints a terrain layer found by reading every patch of a model, saved so that the first
/// layer a later process builds reads only the patches changed since (buildTerrainLayer's `saved`):
/// at 10^6 patches the full read takes minutes. Each footprint is kept with what identifies the
/// data it was made from: the patch's version, child mask, folder and positions file names and
/// boxes (vsm writes a changed patch as a new version in a new folder; a tool that rewrites a
/// patch's positions in place under the same names and boxes must remove the file).
///
/// The bytes (little-endian): "VSMFOOT1", u32 format 1, i32 grid size, u64 count, then `count`
/// records in key order of 58 bytes (u8 depth, u32 x, u32 y, u8 child mask, u64 version, u64 hash
/// of the names and boxes, f64 west, south, east, north), then checksum64 of all before it.
class SavedFootprints {
 public:
  static constexpr std::size_t kRecordBytes = 58;

  /// The footprints of `layer`, built from `model`, of every patch that has one.
  static std::vector<std::byte> encode(const Model& model, const TerrainLayer& layer);
  /// Takes the bytes encode() made for a model of `gridSize`. Throws Error(Corrupt) saying what
  /// is wrong (a short file, another format or grid size, records out of key order, a checksum that
  /// does not match).
  explicit SavedFootprints(std::vector<std::byte> bytes, int gridSize);

  /// The footprint saved for the data `info` describes; nullopt when none was, or for other data.
  std::optional<GeoRect> find(const PatchInfo& info) const;
  std::size_t size() const { return count_; }

 private:
  struct Record {
    PatchKey key;
    std::uint8_t childMask = 0;
    std::uint64_t version = 0;
    std::uint64_t describedBy = 0;
    GeoRect rect;
  };
  Record record(std::size_t i) const;

  /// The file's bytes, records decoded on demand (a model of 10^6 patches saves 80 MB).
  std::vector<std::byte> bytes_;
  std::size_t count_ = 0;
};

}  // namespace vsm::core
