#include "core/diff/diff_picture.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <utility>

#include "core/diff/draw_leaf.hpp"
#include "core/diff/revision_diff.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/opc/texture_file.hpp"

namespace vsm::core {

namespace {

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

namespace diff_detail {

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

}  // namespace diff_detail

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
  const DisplacementStats& t = diff.totals;
  char text[512];
  std::snprintf(text, sizeof text,
                "displacement from revision %llu to %llu along the surface normal, metres: blue "
                "%.6g, white 0, red %+.6g; volume gained %.6g m^3, lost %.6g m^3, changed %.6g "
                "m^2 (significant %.6g m^2)",
                static_cast<unsigned long long>(diff.from),
                static_cast<unsigned long long>(diff.to), -range, range, t.volumeGained,
                t.volumeLost, t.changedArea, t.significantArea);
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
    return encodePng(clear.data(), emptySize, emptySize, 4, text);
  }
  std::vector<std::uint8_t> rgba = colourMap(*diff.map, range);
  drawLegend(rgba, diff.map->grid.width, diff.map->grid.height, range);
  return encodePng(rgba.data(), diff.map->grid.width, diff.map->grid.height, 4, text);
}

}  // namespace vsm::core
