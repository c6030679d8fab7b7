#include "core/diff/revision_diff.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <map>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/merge/merge.hpp"
#include "core/merge/surface_sampler.hpp"
#include "core/opc/texture_file.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "core/tiles/lod_render.hpp"

namespace vsm::core {

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

double dot(const Vec3d& a, const Vec3d& b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}

Vec3d cross(const Vec3d& a, const Vec3d& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

/// `rect` grown by SurfaceSampler::kBorderTolerance of its diagonal on every side: how far
/// outside its cells a surface still answers (as the merge grows its detail footprints).
Rect2d grown(Rect2d rect) {
  if (!rect.empty()) {
    const double margin = SurfaceSampler::kBorderTolerance *
                          std::hypot(rect.max.u - rect.min.u, rect.max.v - rect.min.v);
    rect.min = {rect.min.u - margin, rect.min.v - margin};
    rect.max = {rect.max.u + margin, rect.max.v + margin};
  }
  return rect;
}

/// The leaves of `model` whose footprint in `frame` meets `rect`: a descent from the root through
/// patches whose footprint meets it (a parent's box holds its children's).
std::vector<PatchKey> leavesMeeting(const Model& model, const UpFrame& frame, const Rect2d& rect) {
  std::vector<PatchKey> leaves;
  std::vector<PatchKey> pending{PatchKey::root()};
  while (!pending.empty()) {
    const PatchKey key = pending.back();
    pending.pop_back();
    const PatchInfo* info = model.find(key);
    if (info == nullptr || !grown(frame.footprint(info->globalBox)).intersects(rect)) {
      continue;
    }
    if (info->isLeaf()) {
      leaves.push_back(key);
    } else {
      for (const PatchKey& child : model.children(key)) {
        pending.push_back(child);
      }
    }
  }
  std::sort(leaves.begin(), leaves.end());
  return leaves;
}

/// The unit normal, on the side of `up`, of `grid`'s cell holding grid coordinates (x, y) (as
/// SurfacePoint gives them): of its two diagonals for a full cell, of its triangle for a cell with
/// one undefined corner; NaN when neither exists.
Vec3d cellNormal(const PatchGrid& grid, double x, double y, const Vec3d& up) {
  const int last = grid.size() - 2;
  const int i = std::clamp(static_cast<int>(std::floor(x)), 0, last);
  const int j = std::clamp(static_cast<int>(std::floor(y)), 0, last);
  const std::array<std::pair<int, int>, 4> at{{{i, j}, {i + 1, j}, {i + 1, j + 1}, {i, j + 1}}};
  std::vector<Vec3d> corners;
  for (const auto& [u, v] : at) {
    if (grid.defined(u, v)) {
      corners.push_back(grid.global(u, v));
    }
  }
  Vec3d n{kNaN, kNaN, kNaN};
  if (corners.size() == 4) {
    n = cross(corners[2] - corners[0], corners[3] - corners[1]);
  } else if (corners.size() == 3) {
    n = cross(corners[1] - corners[0], corners[2] - corners[0]);
  }
  const double length = n.norm();
  if (!(length > 0)) {
    return {kNaN, kNaN, kNaN};
  }
  return n * ((dot(n, up) < 0 ? -1.0 : 1.0) / length);
}

/// Each vertex's share of the surface area: a quarter of every full cell around it, a third of
/// every cell with one undefined corner (its triangle).
std::vector<double> vertexAreas(const PatchGrid& grid) {
  const int s = grid.size();
  std::vector<double> areas(grid.vertexCount(), 0.0);
  for (int y = 0; y + 1 < s; ++y) {
    for (int x = 0; x + 1 < s; ++x) {
      const std::array<std::pair<int, int>, 4> at{{{x, y}, {x + 1, y}, {x + 1, y + 1}, {x, y + 1}}};
      std::vector<std::size_t> index;
      std::vector<Vec3d> corners;
      for (const auto& [u, v] : at) {
        if (grid.defined(u, v)) {
          index.push_back(static_cast<std::size_t>(v) * s + u);
          corners.push_back(grid.global(u, v));
        }
      }
      double area = 0;
      if (corners.size() == 4) {
        area = 0.5 * cross(corners[2] - corners[0], corners[3] - corners[1]).norm();
      } else if (corners.size() == 3) {
        area = 0.5 * cross(corners[1] - corners[0], corners[2] - corners[0]).norm();
      } else {
        continue;
      }
      for (const std::size_t k : index) {
        areas[k] += area / static_cast<double>(index.size());
      }
    }
  }
  return areas;
}

/// The other revision's surface around one leaf: a SurfaceSampler over its leaves meeting the
/// leaf, with their grids held (pinned) for the normals. The last one is kept for the next leaf
/// when it needs the same leaves (neighbours mostly do), so a diff holds a few patches at a time.
class OtherSurface {
 public:
  explicit OtherSurface(PatchSource& source) : source_(source) {}

  /// The surface over `box` (a leaf's global box); null when the other revision has none there.
  const SurfaceSampler* around(const Box3d& box) {
    const UpFrame frame(box.center(), upAt(box.center()));
    std::vector<PatchKey> keys = leavesMeeting(source_.model(), frame, grown(frame.footprint(box)));
    if (keys.empty()) {
      return nullptr;
    }
    if (!sampler_ || keys != keys_) {
      sampler_.reset();
      grids_.clear();
      Box3d all;
      noise_ = 0;
      for (const PatchKey& key : keys) {
        grids_.push_back(source_.positions(key));
        const PatchInfo& info = source_.model().at(key);
        all.extend(info.globalBox);
        noise_ = std::max(noise_, storageNoise(info.localBox));
      }
      // One up direction for the whole set, so the sampler is the same whichever leaf built it.
      sampler_.emplace(grids_, defaultUp(all));
      keys_ = std::move(keys);
    }
    return &*sampler_;
  }
  const PatchGrid& grid(std::uint32_t index) const { return *grids_[index]; }
  /// The largest storageNoise of the leaves of the last around().
  double noise() const { return noise_; }
  /// Releases the pins.
  void clear() {
    sampler_.reset();
    grids_.clear();
    keys_.clear();
  }

 private:
  PatchSource& source_;
  std::vector<PatchKey> keys_;
  std::vector<std::shared_ptr<const PatchGrid>> grids_;
  std::optional<SurfaceSampler> sampler_;
  double noise_ = 0;
};

/// One leaf to sample: a changed leaf of `to`, or a leaf of `from` that `to` removed.
struct Work {
  PatchKey key;
  bool removed = false;
};

/// Fills the cells of `grid` whose corners all have a displacement into `map`, interpolated
/// linearly over each cell's two triangles (a 3-corner cell: its triangle).
void drawLeaf(const PatchGrid& grid, const std::vector<double>& d, DisplacementMap& map) {
  const int s = grid.size();
  const TopDownGrid& view = map.grid;
  std::vector<Point2d> pixel(grid.vertexCount());
  for (int y = 0; y < s; ++y) {
    for (int x = 0; x < s; ++x) {
      const std::size_t i = static_cast<std::size_t>(y) * s + x;
      if (std::isfinite(d[i])) {
        pixel[i] = view.pixel(view.plane(grid.global(x, y)));
      }
    }
  }
  const auto triangle = [&](std::size_t a, std::size_t b, std::size_t c) {
    forEachPixelInTriangle(pixel[a], pixel[b], pixel[c], view.width, view.height,
                           [&](int col, int row, double wa, double wb, double wc) {
                             map.values[static_cast<std::size_t>(row) * view.width + col] =
                                 static_cast<float>(wa * d[a] + wb * d[b] + wc * d[c]);
                           });
  };
  for (int y = 0; y + 1 < s; ++y) {
    for (int x = 0; x + 1 < s; ++x) {
      const std::size_t a = static_cast<std::size_t>(y) * s + x, b = a + 1, c = a + s, e = c + 1;
      const bool fa = std::isfinite(d[a]), fb = std::isfinite(d[b]), fc = std::isfinite(d[c]),
                 fe = std::isfinite(d[e]);
      if (fa && fb && fc && fe) {
        triangle(a, c, e);
        triangle(a, e, b);
      } else if (fa + fb + fc + fe == 3) {
        std::vector<std::size_t> rest;
        for (const auto& [k, f] : {std::pair{a, fa}, {b, fb}, {e, fe}, {c, fc}}) {
          if (f) {
            rest.push_back(k);
          }
        }
        triangle(rest[0], rest[1], rest[2]);
      }
    }
  }
}

nlohmann::json number(double v) {
  return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr);
}

nlohmann::json boxJson(const Box3d& box) {
  if (box.empty()) {
    return nullptr;
  }
  return {{"min", {box.min.x, box.min.y, box.min.z}}, {"max", {box.max.x, box.max.y, box.max.z}}};
}

nlohmann::json statsJson(const DisplacementStats& s) {
  const bool any = s.samples > 0;
  return {{"samples", s.samples},
          {"skipped", s.skipped},
          {"area", s.area},
          {"changed_area", s.changedArea},
          {"noise", s.noise},
          {"min", any ? number(s.min) : nullptr},
          {"max", any ? number(s.max) : nullptr},
          {"mean", number(s.mean())},
          {"rms", number(s.rms())},
          {"max_abs", any ? number(s.maxAbs()) : nullptr}};
}

/// 3 x 5 pixel glyphs of what a legend's numbers need, a row per 3 bits (top row first).
struct Glyph {
  char c;
  std::array<std::uint8_t, 5> rows;
};
constexpr std::array<Glyph, 16> kGlyphs{{
    {'0', {7, 5, 5, 5, 7}},
    {'1', {2, 6, 2, 2, 7}},
    {'2', {7, 1, 7, 4, 7}},
    {'3', {7, 1, 7, 1, 7}},
    {'4', {5, 5, 7, 1, 1}},
    {'5', {7, 4, 7, 1, 7}},
    {'6', {7, 4, 7, 5, 7}},
    {'7', {7, 1, 1, 1, 1}},
    {'8', {7, 5, 7, 5, 7}},
    {'9', {7, 5, 7, 1, 7}},
    {'-', {0, 0, 7, 0, 0}},
    {'+', {0, 2, 7, 2, 0}},
    {'.', {0, 0, 0, 0, 2}},
    {'m', {0, 0, 7, 7, 5}},
    {'e', {0, 7, 7, 4, 7}},
    {' ', {0, 0, 0, 0, 0}},
}};

/// Draws the legend into the lower left corner of `rgba` (width x height): a white panel with
/// the colour bar from -range to +range and its ends and middle labelled ("-R m", "0", "+R m"),
/// scaled with the picture; nothing when the picture is too small for it.
void drawLegend(std::vector<std::uint8_t>& rgba, int width, int height, double range) {
  const int s = std::max(1, std::min(width, height) / 256);
  const int pad = 3 * s, barWidth = 100 * s, barHeight = 6 * s, glyph = 5 * s;
  const int panelWidth = barWidth + 2 * pad;
  const int panelHeight = 2 * pad + glyph + 2 * s + barHeight;
  if (width < panelWidth + 8 || height < panelHeight + 8) {
    return;
  }
  const int left = 4, top = height - 4 - panelHeight;
  const auto put = [&](int x, int y, std::array<std::uint8_t, 4> c) {
    std::copy(c.begin(), c.end(), rgba.begin() + (static_cast<std::ptrdiff_t>(y) * width + x) * 4);
  };
  for (int y = 0; y < panelHeight; ++y) {
    for (int x = 0; x < panelWidth; ++x) {
      const bool border = x == 0 || y == 0 || x == panelWidth - 1 || y == panelHeight - 1;
      put(left + x, top + y,
          border ? std::array<std::uint8_t, 4>{96, 96, 96, 255}
                 : std::array<std::uint8_t, 4>{255, 255, 255, 255});
    }
  }
  const int barTop = top + pad + glyph + 2 * s;
  for (int x = 0; x < barWidth; ++x) {
    const double t = (x + 0.5) / barWidth * 2 - 1;
    for (int y = 0; y < barHeight; ++y) {
      put(left + pad + x, barTop + y, divergingColour(t * range, range));
    }
  }
  const auto text = [&](const std::string& label, int x0) {
    for (std::size_t k = 0; k < label.size(); ++k) {
      const auto* g = std::find_if(kGlyphs.begin(), kGlyphs.end(),
                                   [&](const Glyph& c) { return c.c == label[k]; });
      if (g == kGlyphs.end()) {
        continue;
      }
      for (int row = 0; row < 5 * s; ++row) {
        for (int col = 0; col < 3 * s; ++col) {
          if ((g->rows[row / s] >> (2 - col / s)) & 1) {
            put(x0 + static_cast<int>(k) * 4 * s + col, top + pad + row, {0, 0, 0, 255});
          }
        }
      }
    }
  };
  const auto labelWidth = [&](const std::string& label) {
    return static_cast<int>(label.size()) * 4 * s - s;
  };
  char number[32];
  std::snprintf(number, sizeof number, "%.4g", range);
  const std::string low = std::string(range > 0 ? "-" : "") + number + " m";
  const std::string high = std::string(range > 0 ? "+" : "") + number + " m";
  text(low, left + pad);
  text("0", left + pad + barWidth / 2 - labelWidth("0") / 2);
  text(high, left + pad + barWidth - labelWidth(high));
}

}  // namespace

void DisplacementStats::add(double d, double weight, double threshold) {
  ++samples;
  area += weight;
  if (std::abs(d) > threshold) {
    changedArea += weight;
  }
  min = std::min(min, d);
  max = std::max(max, d);
  sum += weight * d;
  sumSquares += weight * d * d;
}

void DisplacementStats::merge(const DisplacementStats& o) {
  samples += o.samples;
  skipped += o.skipped;
  area += o.area;
  changedArea += o.changedArea;
  noise = std::max(noise, o.noise);
  min = std::min(min, o.min);
  max = std::max(max, o.max);
  sum += o.sum;
  sumSquares += o.sumSquares;
}

double storageNoise(const Box3d& localBox) {
  if (localBox.empty()) {
    return 0;
  }
  double sum = 0;
  for (const auto& [lo, hi] : {std::pair{localBox.min.x, localBox.max.x},
                               {localBox.min.y, localBox.max.y},
                               {localBox.min.z, localBox.max.z}}) {
    const double m = std::max(std::abs(lo), std::abs(hi));
    if (m > 0) {
      // float32 has 24 significant bits: in [2^e, 2^(e+1)) the unit in the last place is 2^(e-23).
      const double half = std::ldexp(1.0, static_cast<int>(std::floor(std::log2(m))) - 24);
      sum += half * half;
    }
  }
  return std::sqrt(sum);
}

double DisplacementStats::mean() const {
  return area > 0 ? sum / area : kNaN;
}

double DisplacementStats::rms() const {
  return area > 0 ? std::sqrt(sumSquares / area) : kNaN;
}

double DisplacementStats::maxAbs() const {
  return samples == 0 ? 0.0 : std::max(std::abs(min), std::abs(max));
}

RevisionDiff diffRevisions(LiveModel& live, std::shared_ptr<const ModelSnapshot> from,
                           std::shared_ptr<const ModelSnapshot> to, const DiffOptions& options) {
  const Model& a = *from->model;
  const Model& b = *to->model;
  if (a.empty() || b.empty()) {
    throw Error(ErrorCode::InvalidArgument, "diff: a revision is empty");
  }
  if (a.gridSize() != b.gridSize()) {
    throw Error(ErrorCode::InvalidArgument, "diff: the revisions have different grid sizes");
  }
  if (!(options.epsilon >= 0)) {
    throw Error(ErrorCode::InvalidArgument, "diff: epsilon must be >= 0");
  }
  if (options.mapSize < 0 || options.mapSize > 16384) {
    throw Error(ErrorCode::InvalidArgument, "diff: the map size must be 0..16384 pixels");
  }
  RevisionDiff diff;
  diff.from = from->version;
  diff.to = to->version;
  diff.epsilon = options.epsilon;
  const auto sourceA = liveSource(live, from);
  const auto sourceB = liveSource(live, to);

  // What changed, from the metadata alone.
  std::map<PatchKey, PatchDisplacement> changed;
  std::vector<Work> work;
  for (const auto& [key, info] : b.patches()) {
    const PatchInfo* old = a.find(key);
    if (old != nullptr && old->version == info.version) {
      ++diff.sharedPatches;
      continue;
    }
    changed[key] = {key, info.globalBox, false, info.isLeaf(), {}};
    if (info.isLeaf()) {
      work.push_back({key, false});
    }
  }
  for (const auto& [key, info] : a.patches()) {
    if (b.find(key) == nullptr) {
      changed[key] = {key, info.globalBox, true, info.isLeaf(), {}};
      if (info.isLeaf()) {
        work.push_back({key, true});
      }
    }
  }
  // Shallow to deep: where both revisions' leaves overlap on the map, the finer one is drawn last.
  std::stable_sort(work.begin(), work.end(), [](const Work& x, const Work& y) {
    return x.key.depth != y.key.depth ? x.key.depth < y.key.depth : x.key < y.key;
  });

  OtherSurface surfaceA(*sourceA), surfaceB(*sourceB);
  // One leaf sampled: its grid (pinned) and the displacement at each vertex (NaN where none).
  struct Sampled {
    std::shared_ptr<const PatchGrid> grid;
    std::vector<double> d;
    DisplacementStats stats;
  };
  const auto sample = [&](const Work& w) {
    if (options.cancel != nullptr) {
      options.cancel->throwIfCancelled();
    }
    // The leaf's own revision and the other one.
    PatchSource& own = w.removed ? *sourceA : *sourceB;
    OtherSurface& other = w.removed ? surfaceB : surfaceA;
    const PatchInfo& info = own.model().at(w.key);
    Sampled out{own.positions(w.key), {}, {}};
    const PatchGrid& grid = *out.grid;
    const SurfaceSampler* sampler = other.around(info.globalBox);
    const std::vector<double> areas = vertexAreas(grid);
    out.d.assign(grid.vertexCount(), kNaN);
    if (sampler != nullptr) {
      out.stats.noise = storageNoise(info.localBox) + other.noise();
    }
    const double threshold = std::max(options.epsilon, out.stats.noise);
    const int s = grid.size();
    for (int y = 0; y < s; ++y) {
      for (int x = 0; x < s; ++x) {
        if (!grid.defined(x, y)) {
          continue;
        }
        const Vec3d p = grid.global(x, y);
        const std::optional<SurfacePoint> hit =
            sampler != nullptr ? sampler->locate(p) : std::nullopt;
        const Vec3d n = hit ? cellNormal(other.grid(hit->grid), hit->x, hit->y, sampler->frame().up)
                            : Vec3d{kNaN, kNaN, kNaN};
        if (!n.finite()) {
          ++out.stats.skipped;
          continue;
        }
        // `to` minus `from` along from's normal, or along to's where `to` removed the leaf.
        const double distance = dot(p - hit->position, n);
        const std::size_t i = static_cast<std::size_t>(y) * s + x;
        out.d[i] = w.removed ? -distance : distance;
        out.stats.add(out.d[i], areas[i], threshold);
      }
    }
    return out;
  };

  // The statistics.
  std::vector<bool> leafChanged(work.size(), false);
  for (std::size_t i = 0; i < work.size(); ++i) {
    const DisplacementStats stats = sample(work[i]).stats;
    leafChanged[i] = stats.changedArea > 0;
    diff.totals.merge(stats);
    for (std::optional<PatchKey> k = work[i].key; k; k = k->parent()) {
      const auto it = changed.find(*k);
      if (it != changed.end()) {
        it->second.stats.merge(stats);
      }
    }
    if (options.progress != nullptr) {
      options.progress->report("sampling",
                               static_cast<double>(i + 1) / static_cast<double>(work.size()));
    }
  }

  // The map, over the changed area: the leaves that changed (or every sampled one when none did),
  // and a tenth of that around them for context; their leaves are sampled again to be drawn.
  if (options.mapSize > 0 && !work.empty()) {
    const bool any = std::find(leafChanged.begin(), leafChanged.end(), true) != leafChanged.end();
    TopDownGrid view;
    view.geographic = looksEcef(*sourceB->positions(PatchKey::root()));
    const auto extent = [&](const Work& w) {
      const Box3d& box = (w.removed ? a : b).at(w.key).globalBox;
      Rect2d r;
      for (int c = 0; c < 8 && !box.empty(); ++c) {
        const Point2d p =
            view.plane({(c & 1) ? box.max.x : box.min.x, (c & 2) ? box.max.y : box.min.y,
                        (c & 4) ? box.max.z : box.min.z});
        r.extend({p.x, p.y});
      }
      return r;
    };
    Rect2d area;
    for (std::size_t i = 0; i < work.size(); ++i) {
      if (leafChanged[i] || !any) {
        const Rect2d r = extent(work[i]);
        if (!r.empty()) {
          area.extend(r.min);
          area.extend(r.max);
        }
      }
    }
    if (!area.empty()) {
      const double gu = 0.1 * (area.max.u - area.min.u), gv = 0.1 * (area.max.v - area.min.v);
      area.min = {area.min.u - gu, area.min.v - gv};
      area.max = {area.max.u + gu, area.max.v + gv};
      DisplacementMap& map = diff.map.emplace();
      map.grid = TopDownGrid::fit(view.geographic, area.min.u, area.max.u, area.min.v, area.max.v,
                                  options.mapSize);
      map.values.assign(map.grid.pixels(), std::numeric_limits<float>::quiet_NaN());
      for (std::size_t i = 0; i < work.size(); ++i) {
        if (extent(work[i]).intersects(area)) {
          const Sampled leaf = sample(work[i]);
          drawLeaf(*leaf.grid, leaf.d, map);
        }
        if (options.progress != nullptr) {
          options.progress->report("drawing",
                                   static_cast<double>(i + 1) / static_cast<double>(work.size()));
        }
      }
    }
  }
  surfaceA.clear();
  surfaceB.clear();
  diff.patches.reserve(changed.size());
  for (auto& [key, patch] : changed) {
    diff.patches.push_back(std::move(patch));
  }
  return diff;
}

std::string diffJson(const RevisionDiff& diff, std::string_view model) {
  nlohmann::json patches = nlohmann::json::array();
  std::size_t removed = 0;
  for (const PatchDisplacement& p : diff.patches) {
    removed += p.removed ? 1 : 0;
    nlohmann::json entry = statsJson(p.stats);
    entry["key"] = p.key.toString();
    entry["box"] = boxJson(p.box);
    entry["removed"] = p.removed;
    entry["leaf"] = p.leaf;
    patches.push_back(std::move(entry));
  }
  nlohmann::json totals = statsJson(diff.totals);
  totals["shared_patches"] = diff.sharedPatches;
  totals["changed_patches"] = diff.patches.size() - removed;
  totals["removed_patches"] = removed;
  nlohmann::json body = {{"model", model},   {"from", diff.from},
                         {"to", diff.to},    {"epsilon", diff.epsilon},
                         {"totals", totals}, {"patches", std::move(patches)}};
  if (diff.map) {
    const TopDownGrid& g = diff.map->grid;
    body["map"] = {{"geographic", g.geographic},
                   {"width", g.width},
                   {"height", g.height},
                   {"x0", g.x0},
                   {"y0", g.y0},
                   {"dx", g.dx},
                   {"dy", g.dy}};
  }
  return body.dump();
}

std::array<std::uint8_t, 4> divergingColour(double d, double range) {
  if (!std::isfinite(d)) {
    return {0, 0, 0, 0};
  }
  // ColorBrewer RdBu's ends (#2166ac, #b2182b) through white, linear in sRGB.
  constexpr std::array<double, 3> kBlue{0x21, 0x66, 0xac};
  constexpr std::array<double, 3> kRed{0xb2, 0x18, 0x2b};
  const double t = range > 0 ? std::clamp(d / range, -1.0, 1.0) : 0.0;
  const std::array<double, 3>& end = t < 0 ? kBlue : kRed;
  const double w = std::abs(t);
  std::array<std::uint8_t, 4> out{0, 0, 0, 255};
  for (int c = 0; c < 3; ++c) {
    out[c] = static_cast<std::uint8_t>(std::lround(255 * (1 - w) + end[c] * w));
  }
  return out;
}

std::vector<std::uint8_t> colourMap(const DisplacementMap& map, double range) {
  std::vector<std::uint8_t> rgba(map.values.size() * 4);
  for (std::size_t i = 0; i < map.values.size(); ++i) {
    const auto c = divergingColour(map.values[i], range);
    std::copy(c.begin(), c.end(), rgba.begin() + static_cast<std::ptrdiff_t>(i * 4));
  }
  return rgba;
}

std::string diffLegend(const RevisionDiff& diff) {
  const double range = diff.totals.maxAbs();
  char text[256];
  std::snprintf(text, sizeof text,
                "displacement from revision %llu to %llu along the surface normal, metres: blue "
                "%.6g, white 0, red %+.6g",
                static_cast<unsigned long long>(diff.from),
                static_cast<unsigned long long>(diff.to), -range, range);
  return text;
}

std::vector<std::byte> diffPng(const RevisionDiff& diff, int emptySize) {
  const double range = diff.totals.maxAbs();
  char rangeText[64];
  std::snprintf(rangeText, sizeof rangeText, "%.9g", range);
  const std::vector<std::pair<std::string, std::string>> text{{"Description", diffLegend(diff)},
                                                              {"vsm:range", rangeText}};
  if (!diff.map) {
    const std::vector<std::uint8_t> clear(static_cast<std::size_t>(emptySize) * emptySize * 4, 0);
    return encodePng(clear.data(), emptySize, emptySize, text);
  }
  std::vector<std::uint8_t> rgba = colourMap(*diff.map, range);
  drawLegend(rgba, diff.map->grid.width, diff.map->grid.height, range);
  return encodePng(rgba.data(), diff.map->grid.width, diff.map->grid.height, text);
}

}  // namespace vsm::core
