#pragma once
// A geoid model: orthometric heights (above mean sea level, as most DEMs give them) from heights
// above the WGS 84 ellipsoid (what vsm's models hold), H = h - N.

#include <filesystem>
#include <memory>
#include <string>
#include <vector>

namespace vsm::core {

/// A global grid of geoid undulations N (metres of the geoid above the WGS 84 ellipsoid), read
/// once with GDAL: PROJ's EGM96 grid (Debian package proj-data, which GDAL's PROJ depends on) or
/// any one-band global lon/lat grid GDAL reads (GTX, GeoTIFF). Immutable; thread-safe.
class GeoidGrid {
 public:
  /// The grid at $VSM_GEOID_GRID when set, else the first EGM96 grid PROJ installs
  /// (/usr/share/proj/egm96_15.gtx, /usr/share/proj/us_nga_egm96_15.tif); null when none is
  /// installed. Read at the first call and kept. Throws Error(Corrupt) for a file that is not
  /// such a grid (naming it).
  static std::shared_ptr<const GeoidGrid> installed();
  /// Reads `file`. Throws Error(Corrupt) unless it is one band of posts spanning every longitude
  /// at a constant step in lon/lat degrees.
  static std::shared_ptr<const GeoidGrid> open(const std::filesystem::path& file);

  /// N at a point (degrees), bilinear between the grid's posts; longitudes wrap around.
  double undulation(double lon, double lat) const;
  /// The grid's file name ("egm96_15.gtx"): what the answers name as their height reference.
  const std::string& name() const { return name_; }

 private:
  GeoidGrid() = default;
  std::string name_;
  int width_ = 0, height_ = 0;
  /// The post (0, 0) and the steps (degrees; dLat negative for rows north first).
  double lon0_ = 0, lat0_ = 0, dLon_ = 1, dLat_ = -1;
  std::vector<float> values_;
};

}  // namespace vsm::core
