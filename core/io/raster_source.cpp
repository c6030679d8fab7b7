// Georeferenced height rasters through GDAL: sample (col, row) -> WGS 84 ECEF at its pixel centre.
#include <cpl_error.h>
#include <gdal_priv.h>
#include <ogr_spatialref.h>

#include <array>
#include <cmath>
#include <limits>
#include <memory>
#include <mutex>
#include <numbers>
#include <string>
#include <system_error>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/common/vectorised.hpp"
#include "core/io/gdal_support.hpp"
#include "core/io/grid_source.hpp"

namespace vsm::core {
namespace {

using detail::DirectIo;
using detail::GdalMessagesToLog;
using detail::lastGdalMessage;
using detail::registerGdal;

// WGS 84 ellipsoid (NIMA TR8350.2).
constexpr double kSemiMajor = 6378137.0;
constexpr double kFlattening = 1.0 / 298.257223563;
constexpr double kEccentricity2 = kFlattening * (2.0 - kFlattening);
constexpr double kDegree = std::numbers::pi / 180.0;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

/// Samples per side of the blocks read whole (see RasterSource::block_).
constexpr int kBlockSamples = 1024;

std::string quoted(const std::filesystem::path& path) {
  return "'" + path.string() + "'";
}

struct CoordinateTransformationDeleter {
  void operator()(OGRCoordinateTransformation* ct) const {
    OGRCoordinateTransformation::DestroyCT(ct);
  }
};
using TransformationPtr =
    std::unique_ptr<OGRCoordinateTransformation, CoordinateTransformationDeleter>;

/// True for a geographic CRS in degrees on the WGS 84 datum with the Greenwich meridian: its
/// lon/lat go straight into the ECEF formulas.
bool isWgs84Degrees(const OGRSpatialReference& srs) {
  if (!srs.IsGeographic() || srs.GetPrimeMeridian() != 0.0 ||
      std::fabs(srs.GetAngularUnits() - kDegree) > 1e-15) {
    return false;
  }
  OGRSpatialReference wgs84;
  wgs84.importFromEPSG(4326);
  OGRSpatialReference horizontal(srs);
  if (horizontal.IsCompound()) {
    horizontal.StripVertical();
  }
  if (horizontal.GetAxesCount() == 3) {
    horizontal.DemoteTo2D(nullptr);  // EPSG:4979 is EPSG:4326 plus an ellipsoidal height axis
  }
  return horizontal.IsSameGeogCS(&wgs84) != 0;
}

std::string crsName(const OGRSpatialReference& srs) {
  const char* authority = srs.GetAuthorityName(nullptr);
  const char* code = srs.GetAuthorityCode(nullptr);
  if (authority != nullptr && code != nullptr) {
    return std::string(authority) + ":" + code;
  }
  const char* name = srs.GetName();
  return name != nullptr ? name : "unnamed CRS";
}

/// Metres per unit for the vertical units GDAL drivers report; 1 for metres and unknown units.
double metresPerUnit(const char* unit) {
  const std::string u = unit != nullptr ? unit : "";
  if (u == "ft" || u == "foot" || u == "feet" || u == "international foot") {
    return 0.3048;
  }
  if (u == "US survey foot" || u == "us-ft" || u == "ftUS") {
    return 1200.0 / 3937.0;
  }
  return 1.0;
}

/// Per-row terms of the geodetic -> ECEF formulas for one latitude:
///   X = (N + h) cos(lat) cos(lon), Y = (N + h) cos(lat) sin(lon), Z = (N (1 - e^2) + h) sin(lat)
/// with N = a / sqrt(1 - e^2 sin^2(lat)).
struct LatitudeTerms {
  double nCos = kNaN;  // N cos(lat)
  double cosLat = kNaN;
  double nSin = kNaN;  // N (1 - e^2) sin(lat)
  double sinLat = kNaN;

  static LatitudeTerms at(double latDegrees) {
    if (!(std::fabs(latDegrees) <= 90.0)) {
      return {};  // NaN terms: every vertex of such a row is undefined
    }
    const double lat = latDegrees * kDegree;
    const double s = std::sin(lat);
    const double c = std::cos(lat);
    const double n = kSemiMajor / std::sqrt(1.0 - kEccentricity2 * s * s);
    return {n * c, c, n * (1.0 - kEccentricity2) * s, s};
  }
};

/// ECEF points of a row of n samples of a WGS 84 geographic raster at the latitude of `terms`:
/// (N + h) cos(lat) (cos(lon), sin(lon)), (N (1 - e^2) + h) sin(lat). A NaN height (or NaN
/// terms: a latitude outside +-90) gives NaN coordinates without a test. A loop that
/// vectorises.
VSM_VECTORISED void geographicRow(const LatitudeTerms& terms, const double* __restrict heights,
                                  const double* __restrict cosLon, const double* __restrict sinLon,
                                  int n, Vec3d* __restrict out) {
  const LatitudeTerms t = terms;
  for (int c = 0; c < n; ++c) {
    const double height = heights[c];
    const double radial = t.nCos + height * t.cosLat;  // (N + h) cos(lat)
    out[c] = {radial * cosLon[c], radial * sinLon[c], t.nSin + height * t.sinLat};
  }
}

class RasterSource final : public GridSource {
 public:
  explicit RasterSource(const std::filesystem::path& path) : path_(path) {
    registerGdal();
    const std::string name = path.string();
    if (!name.starts_with("/vsi")) {  // GDAL's virtual file systems have no local file to check
      std::error_code ec;
      if (!std::filesystem::exists(path, ec)) {
        throw Error(ErrorCode::NotFound, "raster " + quoted(path) + " does not exist");
      }
    }
    GdalMessagesToLog quiet;
    CPLErrorReset();
    // The builder reads 257-row windows in quadtree order: through the block cache a striped
    // raster's full-width rows would either stay cached (memory growing with the raster) or be
    // read again for every window.
    const DirectIo direct;
    dataset_.reset(
        GDALDataset::Open(name.c_str(), GDAL_OF_RASTER | GDAL_OF_READONLY | GDAL_OF_VERBOSE_ERROR));
    if (!dataset_) {
      throw Error(ErrorCode::Corrupt,
                  "cannot read raster " + quoted(path) + ": " + lastGdalMessage());
    }
    if (dataset_->GetRasterCount() < 1) {
      throw Error(ErrorCode::InvalidArgument, "raster " + quoted(path) + " has no band");
    }
    band_ = dataset_->GetRasterBand(1);
    width_ = dataset_->GetRasterXSize();
    height_ = dataset_->GetRasterYSize();

    const OGRSpatialReference* crs = dataset_->GetSpatialRef();
    if (crs == nullptr || crs->IsEmpty()) {
      throw Error(ErrorCode::InvalidArgument,
                  "raster " + quoted(path) + " has no coordinate reference system");
    }
    if (dataset_->GetGeoTransform(geoTransform_.data()) != CE_None) {
      throw Error(ErrorCode::InvalidArgument, "raster " + quoted(path) + " has no geotransform");
    }
    if (geoTransform_[2] != 0.0 || geoTransform_[4] != 0.0) {
      throw Error(ErrorCode::InvalidArgument,
                  "raster " + quoted(path) +
                      " has a rotated geotransform; only north-up rasters are supported");
    }

    int hasNoData = 0;
    noData_ = band_->GetNoDataValue(&hasNoData);
    hasNoData_ = hasNoData != 0;
    if (hasNoData_ && band_->GetRasterDataType() == GDT_Float32) {
      // The no-data text may carry fewer digits than the float32 samples: compare as float32.
      noData_ = static_cast<double>(static_cast<float>(noData_));
    }
    int hasScale = 0;
    int hasOffset = 0;
    const double scale = band_->GetScale(&hasScale);
    const double offset = band_->GetOffset(&hasOffset);
    const double unit = metresPerUnit(band_->GetUnitType());
    scale_ = (hasScale != 0 ? scale : 1.0) * unit;
    offset_ = (hasOffset != 0 ? offset : 0.0) * unit;

    OGRSpatialReference source(*crs);
    source.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
    if (isWgs84Degrees(source)) {
      cosLon_.resize(static_cast<std::size_t>(width_));
      sinLon_.resize(static_cast<std::size_t>(width_));
      for (int col = 0; col < width_; ++col) {
        const double lon = (geoTransform_[0] + (col + 0.5) * geoTransform_[1]) * kDegree;
        cosLon_[static_cast<std::size_t>(col)] = std::cos(lon);
        sinLon_[static_cast<std::size_t>(col)] = std::sin(lon);
      }
      latitudes_.resize(static_cast<std::size_t>(height_));
      for (int row = 0; row < height_; ++row) {
        latitudes_[static_cast<std::size_t>(row)] =
            LatitudeTerms::at(geoTransform_[3] + (row + 0.5) * geoTransform_[5]);
      }
    } else {
      // Heights stay the band values: only the horizontal part of the CRS is transformed.
      if (source.IsCompound()) {
        source.StripVertical();
      }
      OGRSpatialReference target;
      target.importFromEPSG(4979);
      target.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
      transform_.reset(OGRCreateCoordinateTransformation(&source, &target));
      if (!transform_) {
        throw Error(ErrorCode::InvalidArgument, "cannot transform the CRS of raster " +
                                                    quoted(path) + " (" + crsName(source) +
                                                    ") to WGS 84: " + lastGdalMessage());
      }
    }
    char* wkt = nullptr;
    const char* const wktOptions[] = {"FORMAT=WKT2_2018", nullptr};
    if (crs->exportToWkt(&wkt, wktOptions) == OGRERR_NONE && wkt != nullptr) {
      crsWkt_ = wkt;
    }
    CPLFree(wkt);
    description_ = std::string(dataset_->GetDriver()->GetDescription()) + " " +
                   std::to_string(width_) + "x" + std::to_string(height_) + ", " + crsName(*crs) +
                   " -> ECEF";
  }

  int width() const override { return width_; }
  int height() const override { return height_; }
  std::string describe() const override { return description_; }
  std::optional<Georeference> georeference() const override {
    Georeference g;
    g.geoTransform = geoTransform_;
    g.crsWkt = crsWkt_;
    return g;
  }
  std::unique_ptr<GridSource> reopen() const override {
    return std::make_unique<RasterSource>(path_);
  }

  void read(int x0, int y0, int w, int h, std::span<Vec3d> out) override {
    const std::size_t count = static_cast<std::size_t>(w) * static_cast<std::size_t>(h);
    if (x0 < 0 || y0 < 0 || w < 0 || h < 0 || x0 + w > width_ || y0 + h > height_ ||
        out.size() < count) {
      throw Error(ErrorCode::Internal, "raster window outside the grid or output too small");
    }
    if (count == 0) {
      return;
    }
    const Heights heights = heightsOf(x0, y0, w, h);
    if (transform_) {
      readTransformed(x0, y0, w, h, heights, out);
      return;
    }
    for (int r = 0; r < h; ++r) {
      geographicRow(latitudes_[static_cast<std::size_t>(y0 + r)], heights.row(r),
                    cosLon_.data() + x0, sinLon_.data() + x0, w,
                    out.data() + static_cast<std::size_t>(r) * w);
    }
  }

 private:
  /// A window's heights: row r starts at first + r * stride.
  struct Heights {
    const double* first;
    std::size_t stride;
    const double* row(int r) const { return first + static_cast<std::size_t>(r) * stride; }
  };

  /// The window's heights in metres, NaN where undefined: inside the block that holds it (read
  /// first if it is not the last one read), or read alone when larger than a block.
  Heights heightsOf(int x0, int y0, int w, int h) {
    if (w > kBlockSamples || h > kBlockSamples) {
      heights_.resize(static_cast<std::size_t>(w) * static_cast<std::size_t>(h));
      readHeights(x0, y0, w, h, heights_.data());
      return {heights_.data(), static_cast<std::size_t>(w)};
    }
    const bool inside = x0 >= block_.x0 && y0 >= block_.y0 && x0 + w <= block_.x0 + block_.w &&
                        y0 + h <= block_.y0 + block_.h;
    if (!inside) {
      // The aligned block of the window's corner, one sample wider and taller than
      // kBlockSamples: the builder's windows start at multiples of their size - 1, a power of 2
      // up to kBlockSamples, so each of them lies inside the block of its corner. (Widening by
      // the window's size, for windows starting anywhere, read 1281^2 samples a block for
      // 1025^2 of 257^2-sample windows: half as much again.) Any other window gets a block that
      // holds at least itself.
      const int bx = x0 / kBlockSamples * kBlockSamples;
      const int by = y0 / kBlockSamples * kBlockSamples;
      const int bw = std::min(width_ - bx, std::max(kBlockSamples + 1, x0 - bx + w));
      const int bh = std::min(height_ - by, std::max(kBlockSamples + 1, y0 - by + h));
      block_.w = block_.h = 0;  // nothing until the read succeeds
      block_.heights.resize(static_cast<std::size_t>(bw) * static_cast<std::size_t>(bh));
      readHeights(bx, by, bw, bh, block_.heights.data());
      block_.x0 = bx;
      block_.y0 = by;
      block_.w = bw;
      block_.h = bh;
    }
    const auto stride = static_cast<std::size_t>(block_.w);
    return {block_.heights.data() + static_cast<std::size_t>(y0 - block_.y0) * stride +
                (x0 - block_.x0),
            stride};
  }

  /// Reads band values of a window into `out` as metres, NaN where undefined.
  void readHeights(int x0, int y0, int w, int h, double* out) {
    const std::size_t count = static_cast<std::size_t>(w) * static_cast<std::size_t>(h);
    GdalMessagesToLog quiet;
    CPLErrorReset();
    if (band_->RasterIO(GF_Read, x0, y0, w, h, out, w, h, GDT_Float64, 0, 0, nullptr) != CE_None) {
      throw Error(CPLGetLastErrorNo() == CPLE_FileIO ? ErrorCode::Io : ErrorCode::Corrupt,
                  "cannot read raster " + quoted(path_) + ": " + lastGdalMessage());
    }
    for (std::size_t i = 0; i < count; ++i) {
      const double v = out[i];
      out[i] = (!std::isfinite(v) || (hasNoData_ && v == noData_)) ? kNaN : v * scale_ + offset_;
    }
  }

  /// Pixel centres through OGR to WGS 84 lon/lat, one batch per row, then the ECEF formulas.
  void readTransformed(int x0, int y0, int w, int h, const Heights& heights, std::span<Vec3d> out) {
    const auto n = static_cast<std::size_t>(w);
    xs_.resize(n);
    ys_.resize(n);
    ok_.resize(n);
    GdalMessagesToLog quiet;
    for (int r = 0; r < h; ++r) {
      const double y = geoTransform_[3] + (y0 + r + 0.5) * geoTransform_[5];
      for (int c = 0; c < w; ++c) {
        xs_[static_cast<std::size_t>(c)] = geoTransform_[0] + (x0 + c + 0.5) * geoTransform_[1];
        ys_[static_cast<std::size_t>(c)] = y;
      }
      transform_->Transform(w, xs_.data(), ys_.data(), nullptr, ok_.data());
      const double* rowHeights = heights.row(r);
      Vec3d* row = out.data() + static_cast<std::size_t>(r) * n;
      for (std::size_t c = 0; c < n; ++c) {
        const double height = rowHeights[c];
        const LatitudeTerms t = LatitudeTerms::at(ys_[c]);
        const double lon = xs_[c] * kDegree;
        if (ok_[c] == 0 || std::isnan(height) || std::isnan(t.cosLat) || !std::isfinite(lon)) {
          row[c] = {kNaN, kNaN, kNaN};
          continue;
        }
        const double radial = t.nCos + height * t.cosLat;
        row[c] = {radial * std::cos(lon), radial * std::sin(lon), t.nSin + height * t.sinLat};
      }
    }
  }

  std::filesystem::path path_;
  GDALDatasetUniquePtr dataset_;
  GDALRasterBand* band_ = nullptr;
  int width_ = 0;
  int height_ = 0;
  std::array<double, 6> geoTransform_{};
  bool hasNoData_ = false;
  double noData_ = 0;
  double scale_ = 1;   // metres per raw band unit, band scale and unit folded in
  double offset_ = 0;  // metres
  std::string description_;
  std::string crsWkt_;

  // WGS 84 geographic rasters: lon depends only on the column and lat only on the row.
  std::vector<double> cosLon_;
  std::vector<double> sinLon_;
  std::vector<LatitudeTerms> latitudes_;
  // Every other CRS: pixel centres go through OGR/PROJ.
  TransformationPtr transform_;

  // The builder asks for patch windows in quadtree order, so the windows of one aligned block of
  // kBlockSamples^2 samples come one after the other: reading the block once costs one read per
  // row of it (direct I/O reads row by row) where its windows would cost one per row of each.
  struct Block {
    int x0 = 0;
    int y0 = 0;
    int w = 0;  // 0: nothing read
    int h = 0;
    std::vector<double> heights;
  };
  Block block_;

  // Buffers reused across reads (heights_: windows larger than a block).
  std::vector<double> heights_;
  std::vector<double> xs_;
  std::vector<double> ys_;
  std::vector<int> ok_;
};

}  // namespace

std::unique_ptr<GridSource> openRasterSource(const std::filesystem::path& path) {
  return std::make_unique<RasterSource>(path);
}

}  // namespace vsm::core
