#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <vector>

#include "core/common/progress.hpp"
#include "core/grid/geometry.hpp"
#include "core/tiles/top_down.hpp"

namespace vsm::core {

class Model;
class PatchGrid;
struct PatchInfo;

/// An sRGB colour, 8 bits per channel.
struct Rgb8 {
  std::uint8_t r = 0, g = 0, b = 0;
  friend bool operator==(const Rgb8&, const Rgb8&) = default;
};

/// The level-of-detail false colours, by patch depth (root = 0): a fixed ramp from dark blue over
/// cyan, green and yellow to dark red (sampled from the "turbo" colour map), shared by
/// `vsm render-lod` and the browser viewer's LOD mode (README.md lists the hex values). Depths past
/// the end take the last colour.
inline constexpr std::array<Rgb8, 16> kDepthPalette{{
    {0x30, 0x12, 0x3b},
    {0x41, 0x45, 0xab},
    {0x46, 0x75, 0xed},
    {0x39, 0xa2, 0xfc},
    {0x1b, 0xcf, 0xd4},
    {0x24, 0xec, 0xa6},
    {0x61, 0xfc, 0x6c},
    {0xa4, 0xfc, 0x3b},
    {0xd1, 0xe8, 0x34},
    {0xf3, 0xc6, 0x3a},
    {0xfe, 0x9b, 0x2d},
    {0xf3, 0x63, 0x15},
    {0xd9, 0x38, 0x06},
    {0xb1, 0x19, 0x01},
    {0x7a, 0x04, 0x02},
    {0x4a, 0x00, 0x00},
}};

/// kDepthPalette[depth], the last entry for deeper patches; precondition depth >= 0.
Rgb8 depthColour(int depth);

/// True when every defined vertex of `grid` lies within 6200..6500 km of the origin: an
/// earth-centred (ECEF) model, as `vsm import` makes from georeferenced rasters.
bool looksEcef(const PatchGrid& grid);

struct LodRenderOptions {
  /// Pixels along the longer side of the image.
  int size = 1024;
  /// Told of the two passes over the leaves ("bounds", "drawing") when given.
  Progress* progress = nullptr;
};

/// A top-down false-colour picture of which depth covers which area.
struct LodImage {
  int width = 0;
  int height = 0;
  /// RGBA, 8 bits each, row-major, top row first; alpha 0 where no leaf is.
  std::vector<std::uint8_t> rgba;
  /// Depth shown per pixel, -1 where no leaf is (same layout).
  std::vector<std::int8_t> depth;
  /// True: x is longitude and y latitude (degrees, WGS 84); false: global x and y.
  bool geographic = false;
  /// Georeferencing: pixel (col, row) covers x in [x0 + col * dx, x0 + (col + 1) * dx] and y in
  /// [y0 - (row + 1) * dy, y0 - row * dy] (north up).
  double x0 = 0, y0 = 0, dx = 1, dy = 1;
  /// Pixels per depth (index = depth), maxDepth() + 1 entries.
  std::vector<std::size_t> pixelsPerDepth;
};

/// Renders the leaves of `model` seen from above: ECEF models (looksEcef() of the root) projected
/// to longitude/latitude with pixels 1/cos(mid-latitude) wider in degrees than tall (so the picture
/// keeps its proportions), other models to their x/y plane. Each complete quad of a leaf is filled
/// with the leaf's depth colour, deeper leaves over shallower ones where they meet. Reads every
/// leaf twice through `load` (extent, then drawing), one at a time.
/// Throws Error(InvalidArgument) for an empty model or size outside 1..16384, and what `load`
/// throws.
LodImage renderLod(const Model& model,
                   const std::function<std::shared_ptr<const PatchGrid>(const PatchInfo&)>& load,
                   const LodRenderOptions& options = {});

}  // namespace vsm::core
