#include "core/tiles/terrain_footprints.hpp"

#include <cstring>
#include <string>

#include "core/common/checksum.hpp"
#include "core/common/error.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

namespace {

constexpr char kMagic[8] = {'V', 'S', 'M', 'F', 'O', 'O', 'T', '1'};
constexpr std::uint32_t kFormat = 1;
constexpr std::size_t kHeadBytes = 8 + 4 + 4 + 8;

/// FNV-1a of what describes the data: its folder and positions file names and its boxes.
std::uint64_t describedBy(const PatchInfo& info) {
  std::uint64_t h = 0xcbf29ce484222325ULL;
  const auto mix = [&h](std::string_view text) {
    for (const char c : text) {
      h = (h ^ static_cast<unsigned char>(c)) * 0x100000001b3ULL;
    }
    h = (h ^ 0xffU) * 0x100000001b3ULL;  // a separator no name holds
  };
  char folder[PatchKey::kMaxText];
  mix(info.folder(folder));
  mix(info.positionsFile());
  for (const Box3d& box : {info.globalBox, info.localBox}) {
    for (const double v : {box.min.x, box.min.y, box.min.z, box.max.x, box.max.y, box.max.z}) {
      mix(std::string_view(reinterpret_cast<const char*>(&v), sizeof v));
    }
  }
  return h;
}

template <typename T>
void put(std::vector<std::byte>& out, const T& value) {
  const auto* p = reinterpret_cast<const std::byte*>(&value);
  out.insert(out.end(), p, p + sizeof(T));
}

template <typename T>
T get(const std::byte* at) {
  T value;
  std::memcpy(&value, at, sizeof(T));
  return value;
}

[[noreturn]] void corrupt(const std::string& what) {
  throw Error(ErrorCode::Corrupt, "saved terrain footprints: " + what);
}

}  // namespace

std::vector<std::byte> SavedFootprints::encode(const Model& model, const TerrainLayer& layer) {
  std::vector<std::byte> out;
  out.reserve(kHeadBytes + layer.footprint.size() * kRecordBytes + 8);
  out.insert(out.end(), reinterpret_cast<const std::byte*>(kMagic),
             reinterpret_cast<const std::byte*>(kMagic) + sizeof kMagic);
  put(out, kFormat);
  put(out, static_cast<std::int32_t>(model.gridSize()));
  const std::size_t countAt = out.size();
  put(out, std::uint64_t{0});
  std::uint64_t count = 0;
  for (const auto& [key, info] : model.patches()) {
    const GeoRect* rect = layer.footprint.find(key);
    if (rect == nullptr) {
      continue;
    }
    put(out, static_cast<std::uint8_t>(key.depth));
    put(out, key.x);
    put(out, key.y);
    put(out, info.childMask);
    put(out, info.version);
    put(out, describedBy(info));
    for (const double v : {rect->west, rect->south, rect->east, rect->north}) {
      put(out, v);
    }
    ++count;
  }
  std::memcpy(out.data() + countAt, &count, sizeof count);
  put(out, checksum64(out));
  return out;
}

SavedFootprints::SavedFootprints(std::vector<std::byte> bytes, int gridSize)
    : bytes_(std::move(bytes)) {
  if (bytes_.size() < kHeadBytes + 8 || std::memcmp(bytes_.data(), kMagic, sizeof kMagic) != 0) {
    corrupt("not a footprints file");
  }
  if (get<std::uint32_t>(bytes_.data() + 8) != kFormat) {
    corrupt("format " + std::to_string(get<std::uint32_t>(bytes_.data() + 8)) + ", not " +
            std::to_string(kFormat));
  }
  if (get<std::int32_t>(bytes_.data() + 12) != gridSize) {
    corrupt("saved for patches of " + std::to_string(get<std::int32_t>(bytes_.data() + 12)) +
            " vertices a side, the model has " + std::to_string(gridSize));
  }
  const auto count = get<std::uint64_t>(bytes_.data() + 16);
  if (count > (bytes_.size() - kHeadBytes - 8) / kRecordBytes ||
      kHeadBytes + count * kRecordBytes + 8 != bytes_.size()) {
    corrupt(std::to_string(count) + " records do not fill " + std::to_string(bytes_.size()) +
            " bytes");
  }
  const std::size_t body = bytes_.size() - 8;
  if (checksum64(std::span<const std::byte>(bytes_).first(body)) !=
      get<std::uint64_t>(bytes_.data() + body)) {
    corrupt("checksum mismatch (damaged)");
  }
  count_ = static_cast<std::size_t>(count);
  for (std::size_t i = 0; i < count_; ++i) {
    const Record r = record(i);
    if (r.key.depth > PatchKey::kMaxDepth || (i > 0 && !(record(i - 1).key < r.key))) {
      corrupt("record " + std::to_string(i) + " is out of key order");
    }
  }
}

SavedFootprints::Record SavedFootprints::record(std::size_t i) const {
  const std::byte* at = bytes_.data() + kHeadBytes + i * kRecordBytes;
  Record r;
  r.key.depth = get<std::uint8_t>(at);
  r.key.x = get<std::uint32_t>(at + 1);
  r.key.y = get<std::uint32_t>(at + 5);
  r.childMask = get<std::uint8_t>(at + 9);
  r.version = get<std::uint64_t>(at + 10);
  r.describedBy = get<std::uint64_t>(at + 18);
  r.rect.west = get<double>(at + 26);
  r.rect.south = get<double>(at + 34);
  r.rect.east = get<double>(at + 42);
  r.rect.north = get<double>(at + 50);
  return r;
}

std::optional<GeoRect> SavedFootprints::find(const PatchInfo& info) const {
  std::size_t lo = 0, hi = count_;
  while (lo < hi) {
    const std::size_t mid = lo + (hi - lo) / 2;
    const std::byte* at = bytes_.data() + kHeadBytes + mid * kRecordBytes;
    const PatchKey key{get<std::uint8_t>(at), get<std::uint32_t>(at + 1),
                       get<std::uint32_t>(at + 5)};
    if (key < info.key) {
      lo = mid + 1;
    } else {
      hi = mid;
    }
  }
  if (lo == count_) {
    return std::nullopt;
  }
  const Record r = record(lo);
  if (r.key != info.key || r.childMask != info.childMask || r.version != info.version ||
      r.describedBy != describedBy(info) || r.rect.empty()) {
    return std::nullopt;
  }
  return r.rect;
}

}  // namespace vsm::core
