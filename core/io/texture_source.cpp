// The image an import drapes over its grid, through GDAL (placement) and OGR (CRS change).
#include "core/io/texture_source.hpp"

#include <cpl_error.h>
#include <gdal_priv.h>
#include <ogr_spatialref.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <mutex>
#include <string>
#include <system_error>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/grid/shaded_relief.hpp"
#include "core/io/gdal_support.hpp"

namespace vsm::core {
namespace {

using detail::GdalMessagesToLog;
using detail::lastGdalMessage;
using detail::registerGdal;

struct TransformDeleter {
  void operator()(OGRCoordinateTransformation* ct) const {
    OGRCoordinateTransformation::DestroyCT(ct);
  }
};

/// A read window is capped at this many times the tile size per axis: a much finer image is read
/// averaged down by GDAL (memory stays a few tiles, whatever the image size).
constexpr int kMaxWindowPerTexel = 2;

/// A tile is filled in bands of this many texel rows, each from its own image window: the
/// coordinates and the window of one band stay a few MB, whatever the tile's size (a whole
/// 4096-texel tile's were 268 MB of coordinates and up to 256 MB of window).
constexpr int kBandRows = 64;

/// The colours at image points (xs[k], ys[k]) (pixel-edge coordinates; NaN: left as they are)
/// into RGBA texels `out`, bilinear between the pixel centres of `buffer`: the image window from
/// (wx0, wy0), read scaled by (scaleX, scaleY) into bw x bh pixels of Bands bytes (grey, grey and
/// alpha, RGB or RGBA); points beyond its edge pixels take them.
template <int Bands>
void sampleWindow(const std::vector<double>& xs, const std::vector<double>& ys, int wx0, int wy0,
                  double scaleX, double scaleY, const std::uint8_t* buffer, int bw, int bh,
                  std::uint8_t* out) {
  const std::size_t rowBytes = static_cast<std::size_t>(bw) * Bands;
  for (std::size_t k = 0; k < xs.size(); ++k) {
    if (std::isnan(xs[k])) {
      continue;
    }
    // Buffer pixel-centre coordinates: centres at integers.
    const double cx = (xs[k] - wx0) * scaleX - 0.5;
    const double cy = (ys[k] - wy0) * scaleY - 0.5;
    const double floorX = std::floor(cx);
    const double floorY = std::floor(cy);
    const auto fx = static_cast<float>(cx - floorX);
    const auto fy = static_cast<float>(cy - floorY);
    const int ix = static_cast<int>(floorX);
    const int iy = static_cast<int>(floorY);
    const std::size_t x0 = static_cast<std::size_t>(std::clamp(ix, 0, bw - 1)) * Bands;
    const std::size_t x1 = static_cast<std::size_t>(std::clamp(ix + 1, 0, bw - 1)) * Bands;
    const std::uint8_t* row0 =
        buffer + static_cast<std::size_t>(std::clamp(iy, 0, bh - 1)) * rowBytes;
    const std::uint8_t* row1 =
        buffer + static_cast<std::size_t>(std::clamp(iy + 1, 0, bh - 1)) * rowBytes;
    const float w00 = (1 - fx) * (1 - fy);
    const float w10 = fx * (1 - fy);
    const float w01 = (1 - fx) * fy;
    const float w11 = fx * fy;
    std::uint8_t v[Bands];
    for (int b = 0; b < Bands; ++b) {
      // The weights sum to 1, so the sum stays in [0, 255] (to float rounding): + 0.5 rounds.
      v[b] = static_cast<std::uint8_t>(w00 * row0[x0 + b] + w10 * row0[x1 + b] +
                                       w01 * row1[x0 + b] + w11 * row1[x1 + b] + 0.5f);
    }
    std::uint8_t* texel = out + k * TextureTile::kChannels;
    if constexpr (Bands <= 2) {
      texel[0] = texel[1] = texel[2] = v[0];
      texel[3] = Bands == 2 ? v[Bands - 1] : 255;
    } else {
      texel[0] = v[0];
      texel[1] = v[1];
      texel[2] = v[2];
      texel[3] = Bands == 4 ? v[Bands - 1] : 255;
    }
  }
}

}  // namespace

struct TextureSource::Impl {
  std::filesystem::path path;
  int gridWidth = 0;
  int gridHeight = 0;
  GDALDatasetUniquePtr dataset;  // guarded by mutex
  int imageWidth = 0;
  int imageHeight = 0;
  int bands = 0;  // bands read: 1 (grey), 2 (grey, alpha), 3 (RGB) or 4 (RGBA)
  bool georeferenced = false;
  std::array<double, 6> gridTransform{};  // grid sample -> grid CRS (pixel-edge convention)
  std::array<double, 6> imageInverse{};   // image CRS -> image pixel (pixel-edge convention)
  std::unique_ptr<OGRCoordinateTransformation, TransformDeleter> transform;  // guarded by mutex
  std::string description;
  mutable std::mutex mutex;  // guards dataset and transform (neither is thread-safe)

  /// Texel rows [j0, j1) of `tile` (f texels per quad side, bottom patch at grid sample (x0, y0);
  /// TextureSource::fillTile), left as they are (transparent) outside the image.
  void fillRows(int x0, int y0, double f, int j0, int j1, TextureTile& tile) const {
    const int t = tile.size();
    const std::size_t n = static_cast<std::size_t>(t) * (j1 - j0);
    std::vector<double> xs(n);
    std::vector<double> ys(n);
    for (int j = j0; j < j1; ++j) {
      for (int i = 0; i < t; ++i) {
        xs[static_cast<std::size_t>(j - j0) * t + i] = x0 + (i + 0.5) / f;
        ys[static_cast<std::size_t>(j - j0) * t + i] = y0 + (j + 0.5) / f;
      }
    }
    {
      std::unique_lock lock(mutex, std::defer_lock);
      if (georeferenced) {
        lock.lock();
      }
      toImage(xs, ys);
    }

    // The image window the texels fall in (pixel-edge coordinates), one pixel of margin for the
    // bilinear neighbours.
    double minX = std::numeric_limits<double>::infinity(), minY = minX;
    double maxX = -minX, maxY = -minX;
    for (std::size_t k = 0; k < n; ++k) {
      if (std::isnan(xs[k]) || xs[k] < 0 || ys[k] < 0 || xs[k] > imageWidth ||
          ys[k] > imageHeight) {
        xs[k] = std::numeric_limits<double>::quiet_NaN();  // outside the image: transparent
        continue;
      }
      minX = std::min(minX, xs[k]);
      maxX = std::max(maxX, xs[k]);
      minY = std::min(minY, ys[k]);
      maxY = std::max(maxY, ys[k]);
    }
    if (!(minX <= maxX)) {
      return;
    }
    const int wx0 = std::max(0, static_cast<int>(std::floor(minX)) - 1);
    const int wy0 = std::max(0, static_cast<int>(std::floor(minY)) - 1);
    const int wx1 = std::min(imageWidth, static_cast<int>(std::ceil(maxX)) + 1);
    const int wy1 = std::min(imageHeight, static_cast<int>(std::ceil(maxY)) + 1);
    const int ww = std::max(1, wx1 - wx0);
    const int wh = std::max(1, wy1 - wy0);
    const int bw = std::min(ww, kMaxWindowPerTexel * t);
    const int bh = std::min(wh, kMaxWindowPerTexel * (j1 - j0));
    const double scaleX = static_cast<double>(bw) / ww;
    const double scaleY = static_cast<double>(bh) / wh;
    std::vector<std::uint8_t> buffer(static_cast<std::size_t>(bw) * bh * bands);
    {
      std::lock_guard lock(mutex);
      GdalMessagesToLog quiet;
      CPLErrorReset();
      GDALRasterIOExtraArg extra;
      INIT_RASTERIO_EXTRA_ARG(extra);
      extra.eResampleAlg = (bw < ww || bh < wh) ? GRIORA_Average : GRIORA_NearestNeighbour;
      std::array<int, 4> bandList{1, 2, 3, 4};
      if (dataset->RasterIO(GF_Read, wx0, wy0, ww, wh, buffer.data(), bw, bh, GDT_Byte, bands,
                            bandList.data(), bands, static_cast<GSpacing>(bw) * bands, 1,
                            &extra) != CE_None) {
        throw Error(CPLGetLastErrorNo() == CPLE_FileIO ? ErrorCode::Io : ErrorCode::Corrupt,
                    "cannot read texture '" + path.string() + "': " + lastGdalMessage());
      }
    }

    std::uint8_t* out =
        tile.texels().data() + static_cast<std::size_t>(j0) * t * TextureTile::kChannels;
    switch (bands) {
      case 1:
        sampleWindow<1>(xs, ys, wx0, wy0, scaleX, scaleY, buffer.data(), bw, bh, out);
        break;
      case 2:
        sampleWindow<2>(xs, ys, wx0, wy0, scaleX, scaleY, buffer.data(), bw, bh, out);
        break;
      case 3:
        sampleWindow<3>(xs, ys, wx0, wy0, scaleX, scaleY, buffer.data(), bw, bh, out);
        break;
      default:
        sampleWindow<4>(xs, ys, wx0, wy0, scaleX, scaleY, buffer.data(), bw, bh, out);
        break;
    }
  }

  /// Image pixel coordinates of grid points (in place: xs, ys in, out); NaN where not placeable.
  /// Caller holds the mutex when georeferenced.
  void toImage(std::vector<double>& xs, std::vector<double>& ys) const {
    const std::size_t n = xs.size();
    if (!georeferenced) {
      const double sx = static_cast<double>(imageWidth) / gridWidth;
      const double sy = static_cast<double>(imageHeight) / gridHeight;
      for (std::size_t i = 0; i < n; ++i) {
        xs[i] = (xs[i] + 0.5) * sx;
        ys[i] = (ys[i] + 0.5) * sy;
      }
      return;
    }
    const auto& g = gridTransform;
    for (std::size_t i = 0; i < n; ++i) {
      const double ex = xs[i] + 0.5;  // sample coordinates to pixel-edge ones
      const double ey = ys[i] + 0.5;
      xs[i] = g[0] + ex * g[1] + ey * g[2];
      ys[i] = g[3] + ex * g[4] + ey * g[5];
    }
    std::vector<int> ok(n, 1);
    if (transform) {
      transform->Transform(static_cast<int>(n), xs.data(), ys.data(), nullptr, ok.data());
    }
    const auto& v = imageInverse;
    for (std::size_t i = 0; i < n; ++i) {
      if (ok[i] == 0 || !std::isfinite(xs[i]) || !std::isfinite(ys[i])) {
        xs[i] = ys[i] = std::numeric_limits<double>::quiet_NaN();
        continue;
      }
      const double x = xs[i];
      const double y = ys[i];
      xs[i] = v[0] + x * v[1] + y * v[2];
      ys[i] = v[3] + x * v[4] + y * v[5];
    }
  }
};

std::string ShadedReliefSource::describe() const {
  return "shaded relief of the surface (sun azimuth " +
         std::to_string(static_cast<int>(kReliefAzimuthDeg)) + " deg, altitude " +
         std::to_string(static_cast<int>(kReliefAltitudeDeg)) + " deg)";
}

void ShadedReliefSource::fillTile(int /*x0*/, int /*y0*/, const PatchGrid& grid,
                                  TextureTile& tile) const {
  TextureTile relief = shadedRelief(grid);
  tile = relief.size() == tile.size() ? std::move(relief) : resizeTile(relief, tile.size());
}

TextureSource::TextureSource(const std::filesystem::path& image, int gridWidth, int gridHeight,
                             const std::optional<Georeference>& grid)
    : impl_(std::make_unique<Impl>()) {
  registerGdal();
  Impl& m = *impl_;
  m.path = image;
  m.gridWidth = gridWidth;
  m.gridHeight = gridHeight;
  std::error_code ec;
  if (!image.string().starts_with("/vsi") && !std::filesystem::exists(image, ec)) {
    throw Error(ErrorCode::NotFound, "texture '" + image.string() + "' does not exist");
  }
  GdalMessagesToLog quiet;
  CPLErrorReset();
  m.dataset.reset(GDALDataset::Open(image.string().c_str(), GDAL_OF_RASTER | GDAL_OF_READONLY));
  if (!m.dataset) {
    throw Error(ErrorCode::Corrupt,
                "cannot read texture '" + image.string() + "': " + lastGdalMessage());
  }
  m.imageWidth = m.dataset->GetRasterXSize();
  m.imageHeight = m.dataset->GetRasterYSize();
  const int count = m.dataset->GetRasterCount();
  if (count < 1 || m.imageWidth < 1 || m.imageHeight < 1) {
    throw Error(ErrorCode::InvalidArgument, "texture '" + image.string() + "' has no pixels");
  }
  m.bands = std::min(count, 4);

  std::array<double, 6> imageTransform{};
  const OGRSpatialReference* imageCrs = m.dataset->GetSpatialRef();
  const bool imageGeo = imageCrs != nullptr && !imageCrs->IsEmpty() &&
                        m.dataset->GetGeoTransform(imageTransform.data()) == CE_None;
  std::string crsText = "no CRS";
  if (imageGeo && grid && !grid->crsWkt.empty()) {
    OGRSpatialReference gridCrs;
    if (gridCrs.importFromWkt(grid->crsWkt.c_str()) != OGRERR_NONE) {
      throw Error(ErrorCode::InvalidArgument, "the grid's CRS cannot be read back");
    }
    gridCrs.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
    OGRSpatialReference target(*imageCrs);
    target.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
    if (!gridCrs.IsSame(&target)) {
      m.transform.reset(OGRCreateCoordinateTransformation(&gridCrs, &target));
      if (!m.transform) {
        throw Error(ErrorCode::InvalidArgument,
                    "cannot transform the grid's CRS to that of texture '" + image.string() +
                        "': " + lastGdalMessage());
      }
    }
    if (GDALInvGeoTransform(imageTransform.data(), m.imageInverse.data()) == 0) {
      throw Error(ErrorCode::InvalidArgument,
                  "texture '" + image.string() + "' has a non-invertible geotransform");
    }
    m.gridTransform = grid->geoTransform;
    m.georeferenced = true;
    const char* authority = imageCrs->GetAuthorityName(nullptr);
    const char* code = imageCrs->GetAuthorityCode(nullptr);
    crsText = authority != nullptr && code != nullptr ? std::string(authority) + ":" + code
                                                      : std::string("a CRS");
  }
  m.description = "'" + image.string() + "': " + m.dataset->GetDriver()->GetDescription() + " " +
                  std::to_string(m.imageWidth) + "x" + std::to_string(m.imageHeight) + " " +
                  std::to_string(count) + " band" + (count == 1 ? "" : "s") + ", " + crsText +
                  (m.georeferenced ? ", georeferenced" : ", stretched over the grid");
}

TextureSource::~TextureSource() = default;

std::string TextureSource::describe() const {
  return impl_->description;
}

bool TextureSource::georeferenced() const {
  return impl_->georeferenced;
}

std::optional<std::pair<double, double>> TextureSource::imagePoint(double gx, double gy) const {
  std::vector<double> xs{gx};
  std::vector<double> ys{gy};
  {
    std::lock_guard lock(impl_->mutex);
    impl_->toImage(xs, ys);
  }
  if (std::isnan(xs[0])) {
    return std::nullopt;
  }
  return std::pair{xs[0], ys[0]};
}

std::optional<double> TextureSource::pixelsPerSample() const {
  const double cx = 0.5 * (impl_->gridWidth - 1);
  const double cy = 0.5 * (impl_->gridHeight - 1);
  std::vector<double> xs{cx, cx + 1, cx};
  std::vector<double> ys{cy, cy, cy + 1};
  {
    std::lock_guard lock(impl_->mutex);
    impl_->toImage(xs, ys);
  }
  const double along = std::hypot(xs[1] - xs[0], ys[1] - ys[0]);
  const double across = std::hypot(xs[2] - xs[0], ys[2] - ys[0]);
  if (!std::isfinite(along) || !std::isfinite(across)) {
    return std::nullopt;
  }
  return std::max(along, across);
}

int TextureSource::naturalTexelsPerQuad(int patchSize) const {
  const std::optional<double> pixels = pixelsPerSample();
  if (!pixels) {
    log::warn("import: the grid's centre cannot be placed on texture " + impl_->description +
              "; one texel per grid quad");
    return 1;
  }
  int f = 1;
  while (f < *pixels / 1.05 && 2 * f <= maxTexelsPerQuad(patchSize)) {
    f *= 2;
  }
  return f;
}

void TextureSource::fillTile(int x0, int y0, const PatchGrid& grid, TextureTile& tile) const {
  const int t = tile.size();
  const double f = static_cast<double>(texelsPerQuadOf(t, grid.size()));
  std::fill(tile.texels().begin(), tile.texels().end(), std::uint8_t{0});
  for (int j0 = 0; j0 < t; j0 += kBandRows) {
    impl_->fillRows(x0, y0, f, j0, std::min(t, j0 + kBandRows), tile);
  }
}

}  // namespace vsm::core
