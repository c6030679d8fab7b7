#include "core/tiles/heights.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <optional>
#include <utility>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

namespace {

constexpr double kA = 6378137.0;
constexpr double kF = 1.0 / 298.257223563;
constexpr double kB = kA * (1 - kF);
constexpr double kE2 = kF * (2 - kF);
constexpr double kEp2 = kE2 / (1 - kE2);
constexpr double kRad = std::numbers::pi / 180.0;
constexpr double kMeanRadius = 6371008.8;

/// The one-pixel picture a point is sampled on: its centre is the point. A pixel of 1e-7 degrees
/// (about 1 cm) keeps the centre within rounding of the point.
constexpr double kPointPixel = 1e-7;

TopDownGrid pointView(const GeoPoint& p) {
  TopDownGrid view;
  view.geographic = true;
  view.dx = view.dy = kPointPixel;
  view.x0 = p.lon - 0.5 * kPointPixel;
  view.y0 = p.lat + 0.5 * kPointPixel;
  view.width = view.height = 1;
  return view;
}

GeoRect viewRect(const TopDownGrid& view, double pad) {
  return {view.x0 - pad * view.dx, view.y0 - (view.height + pad) * view.dy,
          view.x0 + (view.width + pad) * view.dx, view.y0 + pad * view.dy};
}

}  // namespace

Vec3d geodeticOf(const Vec3d& p) {
  const double r = std::sqrt(p.x * p.x + p.y * p.y);
  const double lon = std::atan2(p.y, p.x);
  // tan(theta) = z a / (r b)
  const double tz = p.z * kA, tr = r * kB;
  const double tn = std::sqrt(tz * tz + tr * tr);
  if (!(tn > 0)) {
    return {lon / kRad, 0, -kA};
  }
  const double st = tz / tn, ct = tr / tn;
  const double num = p.z + kEp2 * kB * st * st * st;
  const double den = r - kE2 * kA * ct * ct * ct;
  const double lat = std::atan2(num, den);
  const double len = std::sqrt(num * num + den * den);
  const double sl = num / len, cl = den / len;
  const double n = kA / std::sqrt(1 - kE2 * sl * sl);
  const double h = std::abs(cl) > 1e-9 ? r / cl - n : std::abs(p.z) - n * (1 - kE2);
  return {lon / kRad, lat / kRad, h};
}

void paintHeights(const Model& model, const std::vector<PatchKey>& sources, const TopDownGrid& view,
                  const GeoRect& area, const TerrainGridLoader& load, std::span<double> heights,
                  std::span<std::uint8_t> painted, double edgeTolerance) {
  if (heights.size() != view.pixels() || painted.size() != view.pixels()) {
    throw Error(ErrorCode::InvalidArgument, "paintHeights: the buffers do not match the picture");
  }
  const int width = view.width, height = view.height;
  for (const PatchKey& patchKey : sources) {
    const auto grid = load(model.at(patchKey));
    const int n = grid->size();
    // Blocks of the grid whose four corners lie far from the area are skipped unconverted. The
    // corners' lon/lat, once per lattice point (shared by up to four blocks).
    const int block = std::min(16, n - 1);
    const int lattice = (n - 2) / block + 2;
    std::vector<Point2d> corner(static_cast<std::size_t>(lattice) * lattice);
    const auto cornerAt = [&](int x, int y) -> Point2d& {
      return corner[static_cast<std::size_t>(y == n - 1 ? lattice - 1 : y / block) * lattice +
                    static_cast<std::size_t>(x == n - 1 ? lattice - 1 : x / block)];
    };
    for (int y = 0;; y = std::min(y + block, n - 1)) {
      for (int x = 0;; x = std::min(x + block, n - 1)) {
        if (grid->defined(x, y)) {
          const Vec3d g = geodeticOf(grid->global(x, y));
          cornerAt(x, y) = {g.x, g.y};
        }
        if (x == n - 1) {
          break;
        }
      }
      if (y == n - 1) {
        break;
      }
    }
    std::vector<std::pair<int, int>> blocks;  // the kept blocks' first vertices
    int x0 = n, y0 = n, x1 = -1, y1 = -1;     // the vertices they span
    for (int by = 0; by < n - 1; by += block) {
      for (int bx = 0; bx < n - 1; bx += block) {
        const int ex = std::min(bx + block, n - 1), ey = std::min(by + block, n - 1);
        if (grid->defined(bx, by) && grid->defined(ex, by) && grid->defined(bx, ey) &&
            grid->defined(ex, ey)) {
          GeoRect corners;
          for (const auto& [cx, cy] : {std::pair{bx, by}, {ex, by}, {bx, ey}, {ex, ey}}) {
            const Point2d& g = cornerAt(cx, cy);
            corners.extend(g.x, g.y);
          }
          // The block's surface bulges little beyond its corners: half its size is ample.
          const double padX = (corners.east - corners.west) * 0.5 + 1e-9;
          const double padY = (corners.north - corners.south) * 0.5 + 1e-9;
          if (corners.east - corners.west < 180 &&
              !GeoRect{corners.west - padX, corners.south - padY, corners.east + padX,
                       corners.north + padY}
                   .intersects(area)) {
            continue;
          }
        }
        blocks.emplace_back(bx, by);
        x0 = std::min(x0, bx);
        y0 = std::min(y0, by);
        x1 = std::max(x1, ex);
        y1 = std::max(y1, ey);
      }
    }
    if (blocks.empty()) {
      continue;
    }
    // Pixel position (x, y) and height per vertex of the kept blocks' span, NaN until converted.
    const int spanX = x1 - x0 + 1;
    std::vector<Vec3d> pix(static_cast<std::size_t>(spanX) * (y1 - y0 + 1),
                           Vec3d{std::nan(""), 0, 0});
    const auto convert = [&](int x, int y) -> const Vec3d& {
      Vec3d& p = pix[static_cast<std::size_t>(y - y0) * spanX + static_cast<std::size_t>(x - x0)];
      if (std::isnan(p.x)) {
        const Vec3d g = geodeticOf(grid->global(x, y));
        const Point2d q = view.pixel(view.planeOfLonLat(g.x, g.y));
        p = {q.x, q.y, g.z};
      }
      return p;
    };
    for (const auto& [bx, by] : blocks) {
      const int ex = std::min(bx + block, n - 1), ey = std::min(by + block, n - 1);
      for (int y = by; y < ey; ++y) {
        for (int x = bx; x < ex; ++x) {
          if (!grid->defined(x, y) || !grid->defined(x + 1, y) || !grid->defined(x, y + 1) ||
              !grid->defined(x + 1, y + 1)) {
            continue;
          }
          const Vec3d a = convert(x, y), b = convert(x + 1, y), c = convert(x, y + 1),
                      d = convert(x + 1, y + 1);
          const auto paint = [&](const Vec3d& p, const Vec3d& q, const Vec3d& r) {
            forEachPixelInTriangle(
                {p.x, p.y}, {q.x, q.y}, {r.x, r.y}, width, height,
                [&](int col, int row, double wa, double wb, double wc) {
                  const auto i =
                      static_cast<std::size_t>(row) * width + static_cast<std::size_t>(col);
                  heights[i] = wa * p.z + wb * q.z + wc * r.z;
                  painted[i] = 1;
                },
                edgeTolerance);
          };
          paint(a, c, d);
          paint(a, d, b);
        }
      }
    }
  }
}

std::vector<HeightSample> sampleHeights(const Model& model, const TerrainLayer& layer,
                                        std::span<const GeoPoint> points,
                                        const TerrainGridLoader& load) {
  std::vector<HeightSample> out(points.size());
  for (std::size_t i = 0; i < points.size(); ++i) {
    const TopDownGrid view = pointView(points[i]);
    const GeoRect area = viewRect(view, 1);
    // Leaves only (no resolution is fine enough to stop above them), coarse first.
    for (const PatchKey& source : heightSources(model, layer, area, -1)) {
      double h = 0;
      std::uint8_t painted = 0;
      paintHeights(model, {source}, view, area, load, {&h, 1}, {&painted, 1}, kQueryEdgeTolerance);
      if (painted != 0) {
        out[i] = {h, source.depth, model.at(source).resolution};
      }
    }
  }
  return out;
}

void sampleHeightGrid(const Model& model, const TerrainLayer& layer, const TopDownGrid& view,
                      const TerrainGridLoader& load, std::span<float> out) {
  if (out.size() != view.pixels()) {
    throw Error(ErrorCode::InvalidArgument, "sampleHeightGrid: the buffer does not match");
  }
  std::vector<double> heights(view.pixels(), 0.0);
  std::vector<std::uint8_t> painted(view.pixels(), 0);
  const GeoRect area = viewRect(view, 1);
  paintHeights(model, heightSources(model, layer, area, -1), view, area, load, heights, painted,
               kQueryEdgeTolerance);
  for (std::size_t i = 0; i < out.size(); ++i) {
    out[i] =
        painted[i] != 0 ? static_cast<float>(heights[i]) : std::numeric_limits<float>::quiet_NaN();
  }
}

TopDownGrid heightPicture(const GeoRect& bounds, double resolution, std::size_t maxPixels) {
  if (!(bounds.west < bounds.east) || !(bounds.south < bounds.north)) {
    throw Error(ErrorCode::InvalidArgument,
                "the box must have west < east and south < north (it is inverted or empty)");
  }
  if (!(resolution > 0) || !std::isfinite(resolution)) {
    throw Error(ErrorCode::InvalidArgument, "the resolution must be a positive number");
  }
  const double cols = std::max(1.0, std::round((bounds.east - bounds.west) / resolution));
  const double rows = std::max(1.0, std::round((bounds.north - bounds.south) / resolution));
  if (cols * rows > static_cast<double>(maxPixels)) {
    throw Error(ErrorCode::InvalidArgument,
                "the picture would have " + std::to_string(static_cast<long long>(cols)) + " x " +
                    std::to_string(static_cast<long long>(rows)) + " pixels, more than the " +
                    std::to_string(maxPixels) +
                    " allowed; ask for a smaller box or a coarser "
                    "resolution");
  }
  TopDownGrid view;
  view.geographic = true;
  view.x0 = bounds.west;
  view.y0 = bounds.north;
  view.dx = view.dy = resolution;
  view.width = static_cast<int>(cols);
  view.height = static_cast<int>(rows);
  return view;
}

TopDownGrid pictureRows(const TopDownGrid& view, int row, int rows) {
  TopDownGrid strip = view;
  strip.y0 = view.y0 - row * view.dy;
  strip.height = rows;
  return strip;
}

double finestResolution(const Model& model, const TerrainLayer& layer, const GeoRect& area) {
  double finest = 0;
  for (const PatchKey& leaf : heightSources(model, layer, area, -1)) {
    const double r = model.at(leaf).resolution;
    if (r > 0 && (finest == 0 || r < finest)) {
      finest = r;
    }
  }
  return finest;
}

double finestSpacingDegrees(const Model& model, const TerrainLayer& layer, const GeoRect& area,
                            const TerrainGridLoader& load) {
  std::optional<PatchKey> finest;
  for (const PatchKey& leaf : heightSources(model, layer, area, -1)) {
    if (!finest || model.at(leaf).resolution < model.at(*finest).resolution) {
      finest = leaf;
    }
  }
  if (!finest) {
    return 0;
  }
  const auto grid = load(model.at(*finest));
  const int n = grid->size();
  // The step between the first and last defined vertex of the row (column) with the widest such
  // span, over the cells between them: the float32 rounding of the positions spread over up to
  // n - 1 cells rather than one (a collection's grid drifted 2.5 mm over Jacksboro from one cell).
  const auto step = [&](bool alongRows) {
    double best = 0;
    int widest = 0;
    for (int a = 0; a < n; ++a) {
      int first = -1, last = -1;
      for (int b = 0; b < n; ++b) {
        if (alongRows ? grid->defined(b, a) : grid->defined(a, b)) {
          first = first < 0 ? b : first;
          last = b;
        }
      }
      if (last - first > widest) {
        widest = last - first;
        const Vec3d p = geodeticOf(alongRows ? grid->global(first, a) : grid->global(a, first));
        const Vec3d q = geodeticOf(alongRows ? grid->global(last, a) : grid->global(a, last));
        best = std::hypot(q.x - p.x, q.y - p.y) / widest;
      }
    }
    return best;
  };
  return std::max(step(true), step(false));
}

double greatCircleDistance(const GeoPoint& a, const GeoPoint& b) {
  const double dLat = (b.lat - a.lat) * kRad, dLon = (b.lon - a.lon) * kRad;
  const double s = std::sin(dLat / 2), t = std::sin(dLon / 2);
  const double h = s * s + std::cos(a.lat * kRad) * std::cos(b.lat * kRad) * t * t;
  return 2 * kMeanRadius * std::asin(std::min(1.0, std::sqrt(h)));
}

std::vector<PathSample> samplePath(std::span<const GeoPoint> vertices, std::size_t samples) {
  std::vector<PathSample> out;
  if (vertices.empty()) {
    return out;
  }
  std::vector<double> along(vertices.size(), 0.0);
  for (std::size_t i = 1; i < vertices.size(); ++i) {
    along[i] = along[i - 1] + greatCircleDistance(vertices[i - 1], vertices[i]);
  }
  if (vertices.size() == 1 || samples < 2) {
    out.push_back({vertices.front(), 0});
    return out;
  }
  const double total = along.back();
  std::size_t segment = 0;
  for (std::size_t k = 0; k < samples; ++k) {
    const double d = k + 1 == samples ? total : total * static_cast<double>(k) / (samples - 1);
    while (segment + 2 < vertices.size() && along[segment + 1] < d) {
      ++segment;
    }
    const double length = along[segment + 1] - along[segment];
    const double f = length > 0 ? std::clamp((d - along[segment]) / length, 0.0, 1.0) : 0.0;
    const GeoPoint& p = vertices[segment];
    const GeoPoint& q = vertices[segment + 1];
    out.push_back({{p.lon + f * (q.lon - p.lon), p.lat + f * (q.lat - p.lat)}, d});
  }
  return out;
}

}  // namespace vsm::core
