#include "core/io/geoid.hpp"

#include <gdal_priv.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdlib>
#include <mutex>

#include "core/common/error.hpp"
#include "core/io/gdal_support.hpp"

namespace vsm::core {

namespace fs = std::filesystem;

std::shared_ptr<const GeoidGrid> GeoidGrid::open(const fs::path& file) {
  detail::registerGdal();
  detail::GdalMessagesToLog messages;
  const auto bad = [&](const std::string& why) {
    return Error(ErrorCode::Corrupt, "geoid grid '" + file.string() + "': " + why);
  };
  std::unique_ptr<GDALDataset, void (*)(GDALDataset*)> dataset(
      static_cast<GDALDataset*>(GDALOpen(file.c_str(), GA_ReadOnly)),
      [](GDALDataset* d) { GDALClose(d); });
  if (!dataset) {
    throw bad("GDAL cannot read it: " + detail::lastGdalMessage());
  }
  std::array<double, 6> t{};
  if (dataset->GetRasterCount() != 1 || dataset->GetGeoTransform(t.data()) != CE_None ||
      t[2] != 0 || t[4] != 0 || !(t[1] > 0) || !(t[5] < 0)) {
    throw bad("not one band of a north-up lon/lat grid");
  }
  auto grid = std::shared_ptr<GeoidGrid>(new GeoidGrid);
  grid->name_ = file.filename().string();
  grid->width_ = dataset->GetRasterXSize();
  grid->height_ = dataset->GetRasterYSize();
  grid->dLon_ = t[1];
  grid->dLat_ = t[5];
  // Posts at the pixel centres (as GDAL's GTX driver places them).
  grid->lon0_ = t[0] + t[1] / 2;
  grid->lat0_ = t[3] + t[5] / 2;
  // Every longitude: the posts go round once (the last post may repeat the first).
  const double span = grid->width_ * grid->dLon_;
  if (std::abs(span - 360) > grid->dLon_ + 1e-9 || grid->height_ < 2 || grid->width_ > (1 << 16) ||
      grid->height_ > (1 << 16)) {
    throw bad("it does not span every longitude in at most 65536 x 65536 posts");
  }
  grid->values_.resize(static_cast<std::size_t>(grid->width_) * grid->height_);
  if (dataset->GetRasterBand(1)->RasterIO(GF_Read, 0, 0, grid->width_, grid->height_,
                                          grid->values_.data(), grid->width_, grid->height_,
                                          GDT_Float32, 0, 0) != CE_None) {
    throw bad("cannot read its values: " + detail::lastGdalMessage());
  }
  return grid;
}

std::shared_ptr<const GeoidGrid> GeoidGrid::installed() {
  static std::once_flag once;
  static std::shared_ptr<const GeoidGrid> grid;
  static std::exception_ptr failure;
  std::call_once(once, [] {
    try {
      if (const char* chosen = std::getenv("VSM_GEOID_GRID"); chosen != nullptr && *chosen) {
        grid = open(chosen);
        return;
      }
      for (const char* candidate :
           {"/usr/share/proj/egm96_15.gtx", "/usr/share/proj/us_nga_egm96_15.tif"}) {
        if (fs::exists(candidate)) {
          grid = open(candidate);
          return;
        }
      }
    } catch (...) {
      failure = std::current_exception();
    }
  });
  if (failure) {
    std::rethrow_exception(failure);
  }
  return grid;
}

double GeoidGrid::undulation(double lon, double lat) const {
  // Columns wrap round the globe; rows are clamped at the poles.
  const double columns = 360.0 / dLon_;
  double x = std::fmod((lon - lon0_) / dLon_, columns);
  if (x < 0) {
    x += columns;
  }
  const double y = std::clamp((lat - lat0_) / dLat_, 0.0, height_ - 1.0);
  const int x0 = static_cast<int>(std::floor(x)), y0 = std::min(static_cast<int>(y), height_ - 2);
  const double fx = x - x0, fy = y - y0;
  const auto at = [&](int col, int row) {
    return static_cast<double>(
        values_[static_cast<std::size_t>(row) * width_ + static_cast<std::size_t>(col % width_)]);
  };
  return (1 - fy) * ((1 - fx) * at(x0, y0) + fx * at(x0 + 1, y0)) +
         fy * ((1 - fx) * at(x0, y0 + 1) + fx * at(x0 + 1, y0 + 1));
}

}  // namespace vsm::core
