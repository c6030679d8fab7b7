#include "core/tiles/quantized_mesh.hpp"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <numbers>
#include <optional>
#include <set>
#include <utility>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/grid/vec_ops.hpp"
#include "core/pyramid/model.hpp"
#include "core/tiles/heights.hpp"
#include "core/tiles/lod_render.hpp"
#include "core/tiles/terrain_footprints.hpp"
#include "core/tiles/top_down.hpp"

namespace vsm::core {

static_assert(std::endian::native == std::endian::little,
              "quantized-mesh is little-endian; the encoder copies native values");

namespace {

constexpr double kA = 6378137.0;
constexpr double kF = 1.0 / 298.257223563;
constexpr double kB = kA * (1 - kF);
constexpr double kE2 = kF * (2 - kF);
constexpr double kRad = std::numbers::pi / 180.0;
constexpr int kCells = kTerrainGridSize - 1;  // 64
constexpr int kQuantMax = 32767;

double tileSpan(int z) {
  return 180.0 / static_cast<double>(std::uint64_t{1} << z);
}

/// The tile's rectangle grown by `cells` vertex spacings on every side.
GeoRect grownRect(const TerrainTileKey& key, double cells) {
  GeoRect r = terrainTileRect(key);
  const double d = tileSpan(key.z) / kCells * cells;
  return {r.west - d, r.south - d, r.east + d, r.north + d};
}

/// Bounding tiles of level z that meet `r` (closed rectangles), clamped to the scheme.
TileRange tilesMeeting(int z, const GeoRect& r) {
  const double span = tileSpan(z);
  const auto maxX = static_cast<double>((std::uint64_t{2} << z) - 1);
  const auto maxY = static_cast<double>((std::uint64_t{1} << z) - 1);
  const auto index = [](double v, double hi) {
    return static_cast<std::uint32_t>(std::clamp(std::floor(v), 0.0, hi));
  };
  return {index((r.west + 180) / span, maxX), index((r.south + 90) / span, maxY),
          index((r.east + 180) / span, maxX), index((r.north + 90) / span, maxY)};
}

/// Bound on the tiles of one level of `available` (the level and deeper ones are left out beyond
/// it): layer.json stays small even for a patch whose footprint is huge at its resolution.
constexpr double kMaxAvailableTiles = 1 << 20;

/// A patch's resolution for the level rules: its recorded one, but at least half its footprint's
/// larger side over its cells (never binding for a patch whose grid is filled: its resolution is
/// about the side over the cells), so that a sparse patch (few defined neighbours, a resolution
/// near 0) over a wide area does not count as much finer than its grid can be.
double effectiveResolution(const Model& model, const PatchKey& key, const GeoRect& footprint) {
  const double midLat = (footprint.south + footprint.north) * 0.5 * kRad;
  const double metresPerDegree = kA * kRad;
  const double side =
      std::max((footprint.north - footprint.south) * metresPerDegree,
               (footprint.east - footprint.west) * metresPerDegree * std::cos(midLat));
  return std::max(model.at(key).resolution, side / (2.0 * (model.gridSize() - 1)));
}

/// Whether the root is ECEF and does not fold over itself seen from above; "" when it is a height
/// field, else why not.
std::string heightFieldProblem(const PatchGrid& root) {
  if (!looksEcef(root)) {
    return "its vertices are not earth-centred (ECEF) coordinates 6200..6500 km from the origin, "
           "as vsm import makes from georeferenced rasters: it has no georeference (a point "
           "cloud or a model in a local frame), so it cannot be placed on the globe as terrain";
  }
  const int n = root.size();
  std::vector<Vec3d> geo(root.vertexCount());
  for (int y = 0; y < n; ++y) {
    for (int x = 0; x < n; ++x) {
      if (root.defined(x, y)) {
        geo[static_cast<std::size_t>(y) * n + x] = geodeticOf(root.global(x, y));
      }
    }
  }
  std::size_t positive = 0, negative = 0;
  for (int y = 0; y + 1 < n; ++y) {
    for (int x = 0; x + 1 < n; ++x) {
      if (!root.defined(x, y) || !root.defined(x + 1, y) || !root.defined(x, y + 1)) {
        continue;
      }
      const Vec3d& a = geo[static_cast<std::size_t>(y) * n + x];
      const Vec3d& b = geo[static_cast<std::size_t>(y) * n + x + 1];
      const Vec3d& c = geo[static_cast<std::size_t>(y + 1) * n + x];
      if (std::abs(b.x - a.x) > 180 || std::abs(c.x - a.x) > 180) {
        continue;  // across the antimeridian
      }
      const double area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
      if (area > 0) {
        ++positive;
      } else if (area < 0) {
        ++negative;
      }
    }
  }
  const std::size_t total = positive + negative;
  if (total > 0 && std::min(positive, negative) * 100 > total) {
    return "its surface folds over itself seen from above (" +
           std::to_string(std::min(positive, negative)) + " of " + std::to_string(total) +
           " grid cells face the other way): it is not a height field over the ellipsoid";
  }
  return {};
}

// ---- little-endian output ----------------------------------------------------------------------

class Writer {
 public:
  explicit Writer(std::size_t capacity) { bytes_.reserve(capacity); }
  template <typename T>
  void put(T value) {
    const auto at = bytes_.size();
    bytes_.resize(at + sizeof value);
    std::memcpy(bytes_.data() + at, &value, sizeof value);
  }
  void putBytes(const void* data, std::size_t size) {
    const auto at = bytes_.size();
    bytes_.resize(at + size);
    std::memcpy(bytes_.data() + at, data, size);
  }
  void align(std::size_t to) {
    while (bytes_.size() % to != 0) {
      bytes_.push_back(std::byte{0});
    }
  }
  std::vector<std::byte> take() { return std::move(bytes_); }

 private:
  std::vector<std::byte> bytes_;
};

std::uint16_t zigZag(int value) {
  return static_cast<std::uint16_t>((static_cast<unsigned>(value) << 1) ^
                                    static_cast<unsigned>(value >> 31));
}

using vec::cross;
using vec::dot;

/// Cesium's horizon culling point (EllipsoidalOccluder.computeHorizonCullingPoint) for `points`
/// seen along `direction` (the bounding sphere's centre), in ellipsoid-scaled space. Where no
/// finite point exists (level 0's hemisphere-wide tiles), a point far out along the direction: it
/// culls the tile from cameras behind the globe, right but for a sliver near the limb from which
/// vertices high above the tile's edge could be seen.
Vec3d horizonOcclusionPoint(const std::vector<Vec3d>& points, const Vec3d& direction) {
  const Vec3d scaledDir{direction.x / kA, direction.y / kA, direction.z / kB};
  const double dirNorm = scaledDir.norm();
  if (dirNorm == 0) {
    return {0, 0, 0};
  }
  const Vec3d d = scaledDir * (1 / dirNorm);
  double magnitude = 0;
  for (const Vec3d& p : points) {
    const Vec3d s{p.x / kA, p.y / kA, p.z / kB};
    double m2 = dot(s, s);
    double m = std::sqrt(m2);
    const Vec3d u = s * (1 / m);
    m2 = std::max(1.0, m2);
    m = std::max(1.0, m);
    const double cosAlpha = dot(u, d);
    const double sinAlpha = cross(u, d).norm();
    const double cosBeta = 1 / m;
    const double sinBeta = std::sqrt(m2 - 1) * cosBeta;
    const double denominator = cosAlpha * cosBeta - sinAlpha * sinBeta;
    if (!(denominator > 1e-9)) {
      return d * 1e4;
    }
    magnitude = std::max(magnitude, 1 / denominator);
  }
  return d * magnitude;
}

}  // namespace

// ---- tiling scheme -----------------------------------------------------------------------------

bool TerrainTileKey::valid() const {
  return z >= 0 && z <= kMaxLevel && x < (std::uint64_t{2} << z) && y < (std::uint64_t{1} << z);
}

std::string TerrainTileKey::toString() const {
  return std::to_string(z) + "/" + std::to_string(x) + "/" + std::to_string(y);
}

void GeoRect::extend(double lon, double lat) {
  if (empty()) {
    west = east = lon;
    south = north = lat;
    return;
  }
  west = std::min(west, lon);
  east = std::max(east, lon);
  south = std::min(south, lat);
  north = std::max(north, lat);
}

void GeoRect::extend(const GeoRect& o) {
  if (o.empty()) {
    return;
  }
  extend(o.west, o.south);
  extend(o.east, o.north);
}

double terrainVertexLon(int z, std::uint32_t x, int i) {
  return -180.0 + static_cast<double>(std::int64_t{x} * kCells + i) * tileSpan(z) / kCells;
}

double terrainVertexLat(int z, std::uint32_t y, int j) {
  return std::clamp(
      -90.0 + static_cast<double>(std::int64_t{y} * kCells + j) * tileSpan(z) / kCells, -90.0,
      90.0);
}

GeoRect terrainTileRect(const TerrainTileKey& key) {
  return {terrainVertexLon(key.z, key.x, 0), terrainVertexLat(key.z, key.y, 0),
          terrainVertexLon(key.z, key.x, kCells), terrainVertexLat(key.z, key.y, kCells)};
}

double terrainVertexSpacing(int z) {
  return std::numbers::pi * kA / static_cast<double>(std::uint64_t{1} << z) / kCells;
}

Vec3d geodeticToEcef(double lonDeg, double latDeg, double h) {
  const double lon = lonDeg * kRad, lat = latDeg * kRad;
  const double sl = std::sin(lat), cl = std::cos(lat);
  const double n = kA / std::sqrt(1 - kE2 * sl * sl);
  return {(n + h) * cl * std::cos(lon), (n + h) * cl * std::sin(lon), (n * (1 - kE2) + h) * sl};
}

// ---- layer -------------------------------------------------------------------------------------

const GeoRect* Footprints::find(const PatchKey& key) const {
  if (const auto it = changes_.find(key); it != changes_.end()) {
    return it->second ? &*it->second : nullptr;
  }
  const auto it = base_->find(key);
  return it == base_->end() ? nullptr : &it->second;
}

void Footprints::set(const PatchKey& key, const GeoRect& rect) {
  size_ += find(key) == nullptr ? 1 : 0;
  changes_.insert_or_assign(key, rect);
}

void Footprints::erase(const PatchKey& key) {
  if (find(key) == nullptr) {
    return;
  }
  --size_;
  if (base_->contains(key)) {
    changes_.insert_or_assign(key, std::nullopt);
  } else {
    changes_.erase(key);
  }
}

void Footprints::compact() {
  if (changes_.size() * 32 <= base_->size()) {
    return;
  }
  std::map<PatchKey, GeoRect> merged;
  auto b = base_->begin();
  for (const auto& [key, rect] : changes_) {
    for (; b != base_->end() && b->first < key; ++b) {
      merged.emplace_hint(merged.end(), *b);
    }
    if (b != base_->end() && b->first == key) {
      ++b;
    }
    if (rect) {
      merged.emplace_hint(merged.end(), key, *rect);
    }
  }
  for (; b != base_->end(); ++b) {
    merged.emplace_hint(merged.end(), *b);
  }
  base_ = std::make_shared<const std::map<PatchKey, GeoRect>>(std::move(merged));
  changes_.clear();
}

bool TerrainLayer::isAvailable(const TerrainTileKey& key) const {
  if (!key.valid() || key.z >= static_cast<int>(available.size())) {
    return false;
  }
  for (const TileRange& r : available[static_cast<std::size_t>(key.z)]) {
    if (key.x >= r.startX && key.x <= r.endX && key.y >= r.startY && key.y <= r.endY) {
      return true;
    }
  }
  return false;
}

namespace {

/// Tiles of one level as (y, x), in the order layer.json's runs are made from.
using TileSet = std::set<std::pair<std::uint32_t, std::uint32_t>>;

bool rangeHolds(const TileRange& r, std::uint32_t x, std::uint32_t y) {
  return x >= r.startX && x <= r.endX && y >= r.startY && y <= r.endY;
}

double tileCount(const TileRange& r) {
  return static_cast<double>(r.endX - r.startX + 1) * (r.endY - r.startY + 1);
}

/// The rectangle of a patch's defined vertices and its children's footprints (already in
/// `footprint`); empty when none.
GeoRect footprintOf(const PatchInfo& info, const PatchGrid& grid, const Footprints& footprint) {
  GeoRect rect;
  for (int y = 0; y < grid.size(); ++y) {
    for (int x = 0; x < grid.size(); ++x) {
      if (grid.defined(x, y)) {
        const Vec3d g = geodeticOf(grid.global(x, y));
        rect.extend(g.x, g.y);
      }
    }
  }
  for (const Quadrant q : kQuadrants) {
    if (info.hasChild(q)) {
      if (const GeoRect* child = footprint.find(info.key.child(q))) {
        rect.extend(*child);
      }
    }
  }
  return rect;
}

/// A level's tiles as layer.json lists them: runs along rows, then runs of equal rows merged
/// north.
std::vector<TileRange> rangesOf(const TileSet& tiles) {
  std::vector<TileRange> runs;
  for (auto it = tiles.begin(); it != tiles.end();) {
    TileRange run{it->second, it->first, it->second, it->first};
    for (++it; it != tiles.end() && it->first == run.startY && it->second == run.endX + 1; ++it) {
      ++run.endX;
    }
    runs.push_back(run);
  }
  std::vector<TileRange> merged;
  for (const TileRange& run : runs) {
    auto open = std::find_if(merged.begin(), merged.end(), [&](const TileRange& m) {
      return m.startX == run.startX && m.endX == run.endX && m.endY + 1 == run.startY;
    });
    if (open != merged.end()) {
      open->endY = run.endY;
    } else {
      merged.push_back(run);
    }
  }
  return merged;
}

/// The tiles of level z that meet the footprint of a patch qualifying at z (resolution at most
/// `limit`): from the root down, taking the first qualifying patch of each branch (its footprint
/// holds its descendants'). Sets `tooMany` when the level would list over kMaxAvailableTiles.
void qualifyingTiles(const Model& model, const Footprints& footprint, const PatchKey& key, int z,
                     double limit, TileSet& tiles, bool& tooMany) {
  const GeoRect* fp = footprint.find(key);
  if (fp == nullptr || tooMany) {
    return;
  }
  if (effectiveResolution(model, key, *fp) <= limit) {
    const TileRange r = tilesMeeting(z, *fp);
    if (tileCount(r) + static_cast<double>(tiles.size()) > kMaxAvailableTiles) {
      tooMany = true;
      return;
    }
    for (std::uint32_t y = r.startY; y <= r.endY; ++y) {
      for (std::uint32_t x = r.startX; x <= r.endX; ++x) {
        tiles.emplace(y, x);
      }
    }
    return;
  }
  const PatchInfo& info = model.at(key);
  for (const Quadrant q : kQuadrants) {
    if (info.hasChild(q)) {
      qualifyingTiles(model, footprint, key.child(q), z, limit, tiles, tooMany);
    }
  }
}

/// Whether tile (x, y) of level z meets the footprint of a patch qualifying at z: the descent of
/// qualifyingTiles through the patches whose footprint meets the tile.
bool tileQualifies(const Model& model, const Footprints& footprint, const PatchKey& key, int z,
                   double limit, std::uint32_t x, std::uint32_t y) {
  const GeoRect* fp = footprint.find(key);
  if (fp == nullptr || !rangeHolds(tilesMeeting(z, *fp), x, y)) {
    return false;
  }
  if (effectiveResolution(model, key, *fp) <= limit) {
    return true;
  }
  const PatchInfo& info = model.at(key);
  for (const Quadrant q : kQuadrants) {
    if (info.hasChild(q) && tileQualifies(model, footprint, key.child(q), z, limit, x, y)) {
      return true;
    }
  }
  return false;
}

/// A patch whose footprint or resolution may differ between the previous layer and the new one:
/// both sides (an empty rectangle where a side has none).
struct Moved {
  GeoRect before, after;
  double resolutionBefore = 0, resolutionAfter = 0;
};

}  // namespace

TerrainLayer buildTerrainLayer(const Model& model, const TerrainGridLoader& load,
                               const TerrainLayerBase* previous, const SavedFootprints* saved) {
  if (model.empty()) {
    throw Error(ErrorCode::InvalidArgument, "terrain: the model is empty");
  }
  TerrainLayer layer;
  layer.reason = heightFieldProblem(*load(model.at(PatchKey::root())));
  if (!layer.reason.empty()) {
    return layer;
  }
  layer.heightField = true;
  if (previous != nullptr && !previous->layer.heightField) {
    previous = nullptr;
  }

  // Footprints, deepest first: each patch's own defined vertices and its children's footprints.
  // From a previous layer, only the changed patches and their ancestors are read; the rest keep
  // the previous footprints, and `moved` lists what may differ.
  std::vector<Moved> moved;
  if (previous == nullptr) {
    // A saved footprint stands for its patch unless a child's was read afresh (its data may
    // have changed under an unchanged parent only in a model vsm did not write).
    std::set<PatchKey> read;
    for (const auto& [key, info] : model.patches().reversed()) {
      std::optional<GeoRect> rect = saved != nullptr ? saved->find(info) : std::nullopt;
      for (const Quadrant q : kQuadrants) {
        if (rect && info.hasChild(q) && read.contains(key.child(q))) {
          rect.reset();
        }
      }
      if (!rect) {
        rect = footprintOf(info, *load(info), layer.footprint);
        if (saved != nullptr) {
          read.insert(key);
        }
      }
      if (!rect->empty()) {
        layer.footprint.set(key, *rect);
      }
    }
  } else {
    const ModelChange change =
        previous->change != nullptr ? *previous->change : modelChange(previous->model, model);
    layer.footprint = previous->layer.footprint;
    const auto before = [&](const PatchKey& key) {
      Moved m;
      if (const GeoRect* was = previous->layer.footprint.find(key)) {
        m.before = *was;
        m.resolutionBefore = effectiveResolution(previous->model, key, *was);
      }
      return m;
    };
    for (const PatchKey& key : change.removed) {
      moved.push_back(before(key));
      layer.footprint.erase(key);
    }
    // The changed patches and every ancestor of a changed or removed one.
    std::set<PatchKey> reread(change.changed.begin(), change.changed.end());
    std::set<PatchKey> climbed;
    for (const auto* keys : {&change.changed, &change.removed}) {
      for (const PatchKey& key : *keys) {
        for (auto up = key.parent(); up && climbed.insert(*up).second; up = up->parent()) {
          if (model.find(*up) != nullptr) {
            reread.insert(*up);
          }
        }
      }
    }
    for (auto it = reread.rbegin(); it != reread.rend(); ++it) {
      const PatchInfo& info = model.at(*it);
      Moved m = before(*it);
      m.after = footprintOf(info, *load(info), layer.footprint);
      if (m.after.empty()) {
        layer.footprint.erase(*it);
      } else {
        layer.footprint.set(*it, m.after);
        m.resolutionAfter = effectiveResolution(model, *it, m.after);
      }
      if (!(m.before == m.after) || m.resolutionBefore != m.resolutionAfter) {
        moved.push_back(m);
      }
    }
  }
  layer.footprint.compact();
  if (const GeoRect* root = layer.footprint.find(PatchKey::root())) {
    layer.bounds = *root;  // it holds every other footprint
  }

  // Availability per level. From a previous layer (that listed every level in full), a level
  // changes only in the tiles met by a moved patch that qualifies there before or after: each is
  // asked again, and the level's ranges are remade only when one of them flips.
  const bool byChange = previous != nullptr && !previous->layer.capped;
  layer.available.push_back({TileRange{0, 0, 1, 0}});
  for (int z = 1; z <= TerrainTileKey::kMaxLevel; ++z) {
    const double limit = 2 * terrainVertexSpacing(z);
    TileSet tiles;
    bool tooMany = false;
    const std::vector<TileRange>* was =
        byChange && z < static_cast<int>(previous->layer.available.size())
            ? &previous->layer.available[static_cast<std::size_t>(z)]
            : nullptr;
    if (!byChange) {
      qualifyingTiles(model, layer.footprint, PatchKey::root(), z, limit, tiles, tooMany);
    } else {
      TileSet asked;
      for (const Moved& m : moved) {
        for (const auto& [rect, resolution] :
             {std::pair{m.before, m.resolutionBefore}, std::pair{m.after, m.resolutionAfter}}) {
          if (!rect.empty() && resolution <= limit) {
            const TileRange r = tilesMeeting(z, rect);
            for (std::uint32_t y = r.startY; y <= r.endY; ++y) {
              for (std::uint32_t x = r.startX; x <= r.endX; ++x) {
                asked.emplace(y, x);
              }
            }
          }
        }
      }
      TileSet added, dropped;
      for (const auto& [y, x] : asked) {
        const bool now = tileQualifies(model, layer.footprint, PatchKey::root(), z, limit, x, y);
        const bool then =
            was != nullptr && std::any_of(was->begin(), was->end(),
                                          [&](const TileRange& r) { return rangeHolds(r, x, y); });
        if (now != then) {
          (now ? added : dropped).emplace(y, x);
        }
      }
      if (added.empty() && dropped.empty()) {
        if (was == nullptr || was->empty()) {
          break;
        }
        layer.available.push_back(*was);
        layer.maxZoom = z;
        continue;
      }
      double count = static_cast<double>(added.size());
      for (const TileRange& r : was != nullptr ? *was : std::vector<TileRange>{}) {
        count += tileCount(r);
      }
      if (count > kMaxAvailableTiles) {
        tooMany = true;
      } else {
        for (const TileRange& r : was != nullptr ? *was : std::vector<TileRange>{}) {
          for (std::uint32_t y = r.startY; y <= r.endY; ++y) {
            for (std::uint32_t x = r.startX; x <= r.endX; ++x) {
              tiles.emplace(y, x);
            }
          }
        }
        tiles.merge(added);
        for (const auto& tile : dropped) {
          tiles.erase(tile);
        }
      }
    }
    if (tooMany) {
      layer.capped = true;
      break;
    }
    if (tiles.empty()) {
      break;
    }
    layer.available.push_back(rangesOf(tiles));
    layer.maxZoom = z;
  }
  return layer;
}

std::string terrainMetadataJson(const TerrainLayer& layer, const TerrainTileKey& key) {
  nlohmann::json level = nlohmann::json::array();
  const auto z = static_cast<std::size_t>(key.z) + 1;
  if (z < layer.available.size()) {
    for (const TileRange& r : layer.available[z]) {
      const TileRange c{std::max(r.startX, key.x * 2), std::max(r.startY, key.y * 2),
                        std::min(r.endX, key.x * 2 + 1), std::min(r.endY, key.y * 2 + 1)};
      if (c.startX <= c.endX && c.startY <= c.endY) {
        level.push_back(
            {{"startX", c.startX}, {"startY", c.startY}, {"endX", c.endX}, {"endY", c.endY}});
      }
    }
  }
  nlohmann::json available = nlohmann::json::array();
  if (!level.empty()) {
    available.push_back(std::move(level));
  }
  return nlohmann::json{{"available", std::move(available)}}.dump();
}

std::vector<PatchKey> heightSources(const Model& model, const TerrainLayer& layer,
                                    const GeoRect& area, double spacing) {
  std::vector<PatchKey> sources;
  if (!layer.heightField || model.empty()) {
    return sources;
  }
  std::vector<PatchKey> stack{PatchKey::root()};
  while (!stack.empty()) {
    const PatchKey at = stack.back();
    stack.pop_back();
    const GeoRect* fp = layer.footprint.find(at);
    if (fp == nullptr || !fp->intersects(area)) {
      continue;
    }
    const PatchInfo& info = model.at(at);
    if (info.isLeaf() || effectiveResolution(model, at, *fp) <= spacing) {
      sources.push_back(at);
      continue;
    }
    for (const PatchKey& child : model.children(at)) {
      stack.push_back(child);
    }
  }
  std::sort(sources.begin(), sources.end());  // coarse first (by depth, then row, column)
  return sources;
}

std::vector<PatchKey> terrainSources(const Model& model, const TerrainLayer& layer,
                                     const TerrainTileKey& key) {
  // The ring of one vertex beyond the edges, and a little more for rounding.
  return heightSources(model, layer, grownRect(key, 1.01), terrainVertexSpacing(key.z));
}

// ---- sampling ----------------------------------------------------------------------------------

TerrainHeights sampleTerrain(const Model& model, const std::vector<PatchKey>& sources,
                             const TerrainTileKey& key, const TerrainGridLoader& load) {
  constexpr int kSize = TerrainHeights::kSize;
  TerrainHeights out;
  out.key = key;
  out.h.assign(static_cast<std::size_t>(kSize) * kSize, 0.0);
  std::vector<std::uint8_t> painted(out.h.size(), 0);

  const GeoRect rect = terrainTileRect(key);
  TopDownGrid view;
  view.geographic = true;
  view.dx = view.dy = tileSpan(key.z) / kCells;
  view.x0 = rect.west - 1.5 * view.dx;
  // The unclamped north edge plus the ring (and half a pixel: pixel centres are vertices).
  view.y0 =
      -90.0 + static_cast<double>(std::int64_t{key.y} * kCells + kCells) * view.dy + 1.5 * view.dy;
  view.width = view.height = kSize;
  // Pixel row 0 is the north ring; storage row 0 the south.
  std::vector<double> north(out.h.size(), std::nan(""));
  std::vector<std::uint8_t> paintedNorth(out.h.size(), 0);
  paintHeights(model, sources, view, grownRect(key, 1.5), load, north, paintedNorth);
  for (int row = 0; row < kSize; ++row) {
    for (int col = 0; col < kSize; ++col) {
      const auto from = static_cast<std::size_t>(row) * kSize + static_cast<std::size_t>(col);
      const auto to =
          static_cast<std::size_t>(kSize - 1 - row) * kSize + static_cast<std::size_t>(col);
      if (paintedNorth[from] != 0) {
        out.h[to] = north[from];
        painted[to] = 1;
      }
    }
  }
  for (int j = 0; j < kTerrainGridSize; ++j) {
    for (int i = 0; i < kTerrainGridSize; ++i) {
      out.covered += painted[static_cast<std::size_t>(j + 1) * kSize + i + 1];
    }
  }
  return out;
}

// ---- encoding ----------------------------------------------------------------------------------

std::array<std::uint8_t, 2> octEncode(const Vec3d& v) {
  const double l1 = std::abs(v.x) + std::abs(v.y) + std::abs(v.z);
  double x = v.x / l1, y = v.y / l1;
  if (v.z < 0) {
    const double ox = x;
    x = (1 - std::abs(y)) * (ox < 0 ? -1.0 : 1.0);
    y = (1 - std::abs(ox)) * (y < 0 ? -1.0 : 1.0);
  }
  const auto snorm = [](double value) {
    return static_cast<std::uint8_t>(std::lround((std::clamp(value, -1.0, 1.0) * 0.5 + 0.5) * 255));
  };
  return {snorm(x), snorm(y)};
}

Vec3d octDecode(std::uint8_t ux, std::uint8_t uy) {
  double x = ux / 255.0 * 2 - 1, y = uy / 255.0 * 2 - 1;
  const double z = 1 - (std::abs(x) + std::abs(y));
  if (z < 0) {
    const double ox = x;
    x = (1 - std::abs(y)) * (ox < 0 ? -1.0 : 1.0);
    y = (1 - std::abs(ox)) * (y < 0 ? -1.0 : 1.0);
  }
  const Vec3d n{x, y, z};
  return n * (1 / n.norm());
}

std::vector<std::byte> encodeQuantizedMesh(const TerrainHeights& heights,
                                           const QuantizedMeshOptions& options) {
  constexpr int kN = kTerrainGridSize;
  const TerrainTileKey& key = heights.key;
  if (!key.valid() ||
      heights.h.size() != static_cast<std::size_t>(TerrainHeights::kSize) * TerrainHeights::kSize) {
    throw Error(ErrorCode::InvalidArgument, "quantized-mesh: invalid tile " + key.toString());
  }

  // Heights quantised between float32 bounds that hold every height.
  double lo = std::numeric_limits<double>::infinity(), hi = -lo;
  for (int j = 0; j < kN; ++j) {
    for (int i = 0; i < kN; ++i) {
      lo = std::min(lo, heights.at(i, j));
      hi = std::max(hi, heights.at(i, j));
    }
  }
  float minH = static_cast<float>(lo), maxH = static_cast<float>(hi);
  if (static_cast<double>(minH) > lo) {
    minH = std::nextafter(minH, -std::numeric_limits<float>::infinity());
  }
  if (static_cast<double>(maxH) < hi) {
    maxH = std::nextafter(maxH, std::numeric_limits<float>::infinity());
  }
  const double range = static_cast<double>(maxH) - static_cast<double>(minH);
  const auto quantise = [&](double h) {
    return range > 0 ? static_cast<int>(std::lround((h - minH) / range * kQuantMax)) : 0;
  };

  // Triangles over grid ids (j * 65 + i), two per cell, counter-clockwise seen from above; then
  // vertices renumbered in order of first use, as the high-water-mark code needs.
  std::vector<int> triangles;
  triangles.reserve(static_cast<std::size_t>(kCells) * kCells * 6);
  for (int j = 0; j < kCells; ++j) {
    for (int i = 0; i < kCells; ++i) {
      const int sw = j * kN + i, se = sw + 1, nw = sw + kN, ne = nw + 1;
      triangles.insert(triangles.end(), {sw, se, ne, sw, ne, nw});
    }
  }
  std::vector<int> order(static_cast<std::size_t>(kN) * kN, -1);  // grid id -> vertex index
  std::vector<int> gridOf;                                        // vertex index -> grid id
  gridOf.reserve(order.size());
  for (int& id : triangles) {
    if (order[static_cast<std::size_t>(id)] < 0) {
      order[static_cast<std::size_t>(id)] = static_cast<int>(gridOf.size());
      gridOf.push_back(id);
    }
    id = order[static_cast<std::size_t>(id)];
  }

  // ECEF of grid vertex (i, j) (-1..65 both) at height h, from per-column and per-row terms.
  struct Column {
    double cosLon, sinLon;
  };
  struct Row {
    double cosLat, sinLat, n;
  };
  std::array<Column, TerrainHeights::kSize> columns;
  std::array<Row, TerrainHeights::kSize> rows;
  for (int k = 0; k < TerrainHeights::kSize; ++k) {
    const double lon = terrainVertexLon(key.z, key.x, k - 1) * kRad;
    const double lat = terrainVertexLat(key.z, key.y, k - 1) * kRad;
    columns[static_cast<std::size_t>(k)] = {std::cos(lon), std::sin(lon)};
    const double sl = std::sin(lat);
    rows[static_cast<std::size_t>(k)] = {std::cos(lat), sl, kA / std::sqrt(1 - kE2 * sl * sl)};
  }
  const auto toEcef = [&](int i, int j, double h) {
    const Column& c = columns[static_cast<std::size_t>(i + 1)];
    const Row& r = rows[static_cast<std::size_t>(j + 1)];
    return Vec3d{(r.n + h) * r.cosLat * c.cosLon, (r.n + h) * r.cosLat * c.sinLon,
                 (r.n * (1 - kE2) + h) * r.sinLat};
  };

  // Vertex positions (ECEF, at the heights as decoded) for the bounds.
  std::vector<Vec3d> ecef(gridOf.size());
  std::vector<int> quantised(gridOf.size());
  Box3d box;
  for (std::size_t v = 0; v < gridOf.size(); ++v) {
    const int i = gridOf[v] % kN, j = gridOf[v] / kN;
    quantised[v] = quantise(heights.at(i, j));
    const double h = minH + range * quantised[v] / kQuantMax;
    ecef[v] = toEcef(i, j, h);
    box.extend(ecef[v]);
  }
  const Vec3d centre = box.center();
  double radius = 0;
  for (const Vec3d& p : ecef) {
    radius = std::max(radius, (p - centre).norm());
  }
  radius = radius * (1 + 1e-9) + 1e-3;
  const Vec3d horizon = horizonOcclusionPoint(ecef, centre);

  // Header, vertices, indices, edges, normals, metadata.
  Writer w(88 + 4 + 6 * kN * kN + 2 + 4 + 6 * kCells * kCells * 2 + 4 * (4 + 2 * kN) + 5 +
           2 * kN * kN + 9 + options.metadata.size());
  for (const double value : {centre.x, centre.y, centre.z}) {
    w.put(value);
  }
  w.put(minH);
  w.put(maxH);
  for (const double value :
       {centre.x, centre.y, centre.z, radius, horizon.x, horizon.y, horizon.z}) {
    w.put(value);
  }
  w.put(static_cast<std::uint32_t>(gridOf.size()));
  const auto putDeltas = [&](const auto& valueOf) {
    int previous = 0;
    for (std::size_t v = 0; v < gridOf.size(); ++v) {
      const int value = valueOf(v);
      w.put(zigZag(value - previous));
      previous = value;
    }
  };
  const auto uOf = [&](std::size_t v) { return (gridOf[v] % kN) * kQuantMax / kCells; };
  const auto vOf = [&](std::size_t v) { return (gridOf[v] / kN) * kQuantMax / kCells; };
  putDeltas(uOf);
  putDeltas(vOf);
  putDeltas([&](std::size_t v) { return quantised[v]; });

  w.align(2);
  w.put(static_cast<std::uint32_t>(triangles.size() / 3));
  int highest = 0;
  for (const int index : triangles) {
    w.put(static_cast<std::uint16_t>(highest - index));
    if (index == highest) {
      ++highest;
    }
  }
  const auto putEdge = [&](auto gridId) {
    w.put(static_cast<std::uint32_t>(kN));
    for (int k = 0; k < kN; ++k) {
      w.put(static_cast<std::uint16_t>(order[static_cast<std::size_t>(gridId(k))]));
    }
  };
  putEdge([](int k) { return k * kN; });           // west, south to north
  putEdge([](int k) { return k; });                // south, west to east
  putEdge([](int k) { return k * kN + kCells; });  // east, south to north
  putEdge([](int k) { return kCells * kN + k; });  // north, west to east

  if (options.normals) {
    // From the unquantised heights of the vertex's four neighbours (the ring at the edges), so
    // neighbouring tiles compute the same normal for a shared vertex.
    std::vector<Vec3d> positions(heights.h.size());
    for (int j = -1; j <= kN; ++j) {
      for (int i = -1; i <= kN; ++i) {
        positions[static_cast<std::size_t>(j + 1) * TerrainHeights::kSize +
                  static_cast<std::size_t>(i + 1)] = toEcef(i, j, heights.at(i, j));
      }
    }
    const auto position = [&](int i, int j) -> const Vec3d& {
      return positions[static_cast<std::size_t>(j + 1) * TerrainHeights::kSize +
                       static_cast<std::size_t>(i + 1)];
    };
    w.put(std::uint8_t{1});
    w.put(static_cast<std::uint32_t>(gridOf.size() * 2));
    for (const int id : gridOf) {
      const int i = id % kN, j = id / kN;
      Vec3d normal =
          cross(position(i + 1, j) - position(i - 1, j), position(i, j + 1) - position(i, j - 1));
      double length = normal.norm();
      if (!(length > 0) || !std::isfinite(length)) {
        // Degenerate (at a pole): the ellipsoid's normal.
        const double lon = terrainVertexLon(key.z, key.x, i) * kRad;
        const double lat = terrainVertexLat(key.z, key.y, j) * kRad;
        normal = {std::cos(lat) * std::cos(lon), std::cos(lat) * std::sin(lon), std::sin(lat)};
        length = 1;
      }
      const auto oct = octEncode(normal * (1 / length));
      w.put(oct[0]);
      w.put(oct[1]);
    }
  }
  if (!options.metadata.empty()) {
    w.put(std::uint8_t{4});
    w.put(static_cast<std::uint32_t>(4 + options.metadata.size()));
    w.put(static_cast<std::uint32_t>(options.metadata.size()));
    w.putBytes(options.metadata.data(), options.metadata.size());
  }
  return w.take();
}

}  // namespace vsm::core
