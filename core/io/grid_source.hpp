#pragma once

#include <filesystem>
#include <memory>
#include <span>
#include <string>

#include "core/common/executor.hpp"
#include "core/common/progress.hpp"
#include "core/grid/geometry.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

/// Vertex positions laid out on a width x height grid: a raster, an organized point cloud.
/// Grid neighbours are surface neighbours.
class GridSource {
 public:
  virtual ~GridSource() = default;
  virtual int width() const = 0;
  virtual int height() const = 0;
  /// A one-line description for logs and `vsm info` ("GeoTIFF 1405x621, EPSG:4326 -> ECEF").
  virtual std::string describe() const = 0;
  /// Fills `out` (w * h entries, row-major) with the global positions of the window
  /// [x0, x0 + w) x [y0, y0 + h); NaN for undefined samples. The window lies inside the grid.
  /// Throws Error(Io / Corrupt) when the source cannot be read.
  virtual void read(int x0, int y0, int w, int h, std::span<Vec3d> out) = 0;
};

struct ImportOptions {
  /// Vertices per patch side: 2^n + 1.
  int patchSize = 257;
  Progress* progress = nullptr;
  const CancelToken* cancel = nullptr;
  /// When given, the four quarters below the root are built as parallel tasks (the source is
  /// read under a lock: GDAL datasets are not thread-safe). Progress is reported from them under
  /// a lock too.
  Executor* executor = nullptr;
};

/// Builds the full pyramid of `source` (bottom patches with one line of overlap, padded with
/// undefined vertices, every overview by reduction, empty patches omitted) and writes it as a new
/// OPC directory `outDir`. Works patch by patch (memory stays a few patches per level, whatever the
/// source size). Writes into a staging directory beside `outDir` and renames it into place only
/// when complete, so no half-written model is ever left at `outDir`.
///
/// Throws Error(Conflict) when outDir exists, Error(InvalidArgument) when the source has no defined
/// sample or the patch size is invalid, Error(Cancelled), or the source's errors.
Model buildOpc(GridSource& source, const std::filesystem::path& outDir,
               const ImportOptions& options);

/// Opens a georeferenced raster through GDAL (first band = height). Geographic rasters become
/// WGS 84 ECEF metres, projected rasters are transformed to ECEF through GDAL/PROJ; sample (col,
/// row) becomes the vertex at its pixel centre; no-data and NaN become undefined.
/// Throws Error(NotFound / InvalidArgument (no CRS, unsupported CRS, rotated geotransform) /
/// Corrupt).
std::unique_ptr<GridSource> openRasterSource(const std::filesystem::path& path);

/// Opens an organized point cloud: PCL `.pcd` with width x height > 1 rows, or a PLY grid (a
/// vertex list with `obj_info num_cols/num_rows`, or an organized PCL-written PLY), keeping grid
/// order. Non-finite points become undefined. Coordinates are taken as global Cartesian metres.
/// Throws Error(NotFound / InvalidArgument (unorganized cloud) / Corrupt).
std::unique_ptr<GridSource> openCloudSource(const std::filesystem::path& path);

/// Chooses the reader by extension (.pcd, .ply: cloud; anything else: GDAL raster) and builds.
Model importFile(const std::filesystem::path& input, const std::filesystem::path& outDir,
                 const ImportOptions& options);

}  // namespace vsm::core
