#include "core/io/geotiff.hpp"

#include <gdal_priv.h>
#include <ogr_spatialref.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <exception>
#include <limits>
#include <memory>
#include <string>

#include "core/common/error.hpp"
#include "core/durable/durable_io.hpp"
#include "core/io/gdal_support.hpp"

namespace vsm::core {

void writeFloatGeoTiff(const std::filesystem::path& file, const FloatRaster& raster) {
  if (raster.width < 1 || raster.height < 1 ||
      raster.values.size() != static_cast<std::size_t>(raster.width) * raster.height) {
    throw Error(ErrorCode::InvalidArgument, "GeoTIFF: the raster's size does not match its values");
  }
  detail::registerGdal();
  detail::GdalMessagesToLog messages;
  GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("GTiff");
  if (driver == nullptr) {
    throw Error(ErrorCode::Internal, "GDAL has no GTiff driver");
  }
  const std::filesystem::path temporary =
      file.parent_path() / ("." + file.filename().string() + ".tmp-" + std::to_string(::getpid()));
  const auto fail = [&](const std::string& what) {
    const std::string message = detail::lastGdalMessage();
    std::error_code ignored;
    std::filesystem::remove(temporary, ignored);
    return Error(ErrorCode::Io, "cannot write '" + file.string() + "': " + what + ": " + message);
  };
  {
    char** creation = nullptr;
    creation = CSLSetNameValue(creation, "COMPRESS", "DEFLATE");
    creation = CSLSetNameValue(creation, "PREDICTOR", "3");
    creation = CSLSetNameValue(creation, "TILED", "YES");
    std::unique_ptr<GDALDataset, void (*)(GDALDataset*)> dataset(
        driver->Create(temporary.c_str(), raster.width, raster.height, 1, GDT_Float32, creation),
        [](GDALDataset* d) { GDALClose(d); });
    CSLDestroy(creation);
    if (!dataset) {
      throw fail("create");
    }
    std::array<double, 6> transform = raster.geoTransform;
    if (dataset->SetGeoTransform(transform.data()) != CE_None) {
      throw fail("geotransform");
    }
    if (raster.wgs84) {
      OGRSpatialReference srs;
      srs.importFromEPSG(4326);
      srs.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
      if (dataset->SetSpatialRef(&srs) != CE_None) {
        throw fail("spatial reference");
      }
    }
    GDALRasterBand* band = dataset->GetRasterBand(1);
    if (band->SetNoDataValue(std::nan("")) != CE_None ||
        band->RasterIO(GF_Write, 0, 0, raster.width, raster.height,
                       const_cast<float*>(raster.values.data()), raster.width, raster.height,
                       GDT_Float32, 0, 0) != CE_None) {
      throw fail("pixels");
    }
    // Closing writes what GDAL still holds; its errors are only reported through CPLError.
    CPLErrorReset();
    GDALClose(dataset.release());
    if (CPLGetLastErrorType() == CE_Failure || CPLGetLastErrorType() == CE_Fatal) {
      throw fail("close");
    }
  }
  durable::syncFile(temporary);
  durable::replaceFile(temporary, file);
}

}  // namespace vsm::core

namespace vsm::core {

namespace {

/// A GDAL dataset whose one band's blocks are the raster's strips, made on demand by `fill`: the
/// COG driver copies from it block by block. What `fill` throws is kept (GDAL's C++ is not
/// exception-safe) and thrown after the copy fails.
class StripDataset final : public GDALDataset {
 public:
  explicit StripDataset(const StripRaster& raster);
  CPLErr GetGeoTransform(double* transform) override {
    std::copy(raster_.geoTransform.begin(), raster_.geoTransform.end(), transform);
    return CE_None;
  }
  const OGRSpatialReference* GetSpatialRef() const override {
    return raster_.wgs84 ? &srs_ : nullptr;
  }
  const StripRaster& raster() const { return raster_; }
  std::exception_ptr failure;

 private:
  const StripRaster& raster_;
  OGRSpatialReference srs_;
};

class StripBand final : public GDALRasterBand {
 public:
  explicit StripBand(StripDataset* dataset) {
    poDS = dataset;
    nBand = 1;
    eDataType = GDT_Float32;
    nRasterXSize = dataset->raster().width;
    nRasterYSize = dataset->raster().height;
    nBlockXSize = nRasterXSize;
    nBlockYSize = StripRaster::kRows;
  }
  double GetNoDataValue(int* success) override {
    if (success != nullptr) {
      *success = TRUE;
    }
    return std::nan("");
  }

 protected:
  CPLErr IReadBlock(int, int blockY, void* data) override {
    auto* dataset = static_cast<StripDataset*>(poDS);
    const StripRaster& r = dataset->raster();
    const int row = blockY * StripRaster::kRows;
    const int rows = std::min(StripRaster::kRows, r.height - row);
    auto* values = static_cast<float*>(data);
    std::fill(values, values + static_cast<std::size_t>(nBlockXSize) * nBlockYSize,
              std::numeric_limits<float>::quiet_NaN());
    try {
      r.fill(row, rows, std::span<float>(values, static_cast<std::size_t>(rows) * r.width));
      return CE_None;
    } catch (...) {
      dataset->failure = std::current_exception();
      CPLError(CE_Failure, CPLE_AppDefined, "the heights could not be sampled");
      return CE_Failure;
    }
  }
};

StripDataset::StripDataset(const StripRaster& raster) : raster_(raster) {
  nRasterXSize = raster.width;
  nRasterYSize = raster.height;
  eAccess = GA_ReadOnly;
  srs_.importFromEPSG(4326);
  srs_.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
  SetBand(1, new StripBand(this));  // the dataset owns its bands
}

/// Copies `raster` to `target` (a file or a /vsimem/ name) with the COG driver.
void copyToCog(const std::string& target, const StripRaster& raster) {
  if (raster.width < 1 || raster.height < 1 || !raster.fill) {
    throw Error(ErrorCode::InvalidArgument, "GeoTIFF: the raster is empty");
  }
  detail::registerGdal();
  detail::GdalMessagesToLog messages;
  GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("COG");
  if (driver == nullptr) {
    throw Error(ErrorCode::Internal, "GDAL has no COG driver");
  }
  StripDataset source(raster);
  char** options = nullptr;
  options = CSLSetNameValue(options, "COMPRESS", "DEFLATE");
  options = CSLSetNameValue(options, "PREDICTOR", "YES");
  options = CSLSetNameValue(options, "BLOCKSIZE", std::to_string(StripRaster::kRows).c_str());
  options = CSLSetNameValue(options, "OVERVIEWS", "NONE");
  options = CSLSetNameValue(options, "NUM_THREADS", "1");
  CPLErrorReset();
  GDALDataset* out = driver->CreateCopy(target.c_str(), &source, FALSE, options, nullptr, nullptr);
  CSLDestroy(options);
  const bool failed = out == nullptr || CPLGetLastErrorType() == CE_Failure;
  if (out != nullptr) {
    GDALClose(out);
  }
  if (source.failure) {
    VSIUnlink(target.c_str());
    std::rethrow_exception(source.failure);
  }
  if (failed || CPLGetLastErrorType() == CE_Failure) {
    const std::string message = detail::lastGdalMessage();
    VSIUnlink(target.c_str());
    throw Error(ErrorCode::Io, "cannot write the GeoTIFF '" + target + "': " + message);
  }
}

}  // namespace

void writeCogGeoTiff(const std::filesystem::path& file, const StripRaster& raster) {
  const std::filesystem::path temporary =
      file.parent_path() / ("." + file.filename().string() + ".tmp-" + std::to_string(::getpid()));
  copyToCog(temporary.string(), raster);
  durable::syncFile(temporary);
  durable::replaceFile(temporary, file);
}

std::vector<std::byte> encodeCogGeoTiff(const StripRaster& raster) {
  static std::atomic<std::uint64_t> counter{0};
  const std::string name = "/vsimem/vsm-cog-" + std::to_string(::getpid()) + "-" +
                           std::to_string(counter.fetch_add(1)) + ".tif";
  copyToCog(name, raster);
  vsi_l_offset length = 0;
  GByte* data = VSIGetMemFileBuffer(name.c_str(), &length, FALSE);
  std::vector<std::byte> bytes;
  if (data != nullptr) {
    const auto* begin = reinterpret_cast<const std::byte*>(data);
    bytes.assign(begin, begin + length);
  }
  VSIUnlink(name.c_str());
  if (bytes.empty()) {
    throw Error(ErrorCode::Io, "the GeoTIFF made in memory is empty");
  }
  return bytes;
}

}  // namespace vsm::core
