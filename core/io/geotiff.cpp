#include "core/io/geotiff.hpp"

#include <gdal_priv.h>
#include <ogr_spatialref.h>
#include <unistd.h>

#include <cmath>
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
