#pragma once

#include <array>
#include <filesystem>
#include <memory>
#include <optional>
#include <span>
#include <string>

#include "core/common/executor.hpp"
#include "core/common/progress.hpp"
#include "core/grid/geometry.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

/// Where a georeferenced grid lies: sample (col, row) has its pixel centre at
/// (gt[0] + (col + 0.5) gt[1] + (row + 0.5) gt[2], gt[3] + (col + 0.5) gt[4] + (row + 0.5) gt[5])
/// in the CRS `crsWkt` (GDAL's geotransform convention; x = easting/longitude).
struct Georeference {
  std::array<double, 6> geoTransform{};
  std::string crsWkt;
};

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
  /// The grid's georeference when it has one (rasters); nullopt otherwise (point clouds).
  virtual std::optional<Georeference> georeference() const { return std::nullopt; }
  /// Another handle of the same source for another thread (reads through it need no lock), or
  /// null when the source has none to give (then one handle is shared under a lock).
  virtual std::unique_ptr<GridSource> reopen() const { return nullptr; }
};

struct ImportOptions {
  /// Vertices per patch side: 2^n + 1.
  int patchSize = 257;
  Progress* progress = nullptr;
  const CancelToken* cancel = nullptr;
  /// When given, the subtrees two levels below the root are built as parallel tasks, each reading
  /// through its own handle of the source (GridSource::reopen; GDAL datasets are not thread-safe),
  /// or under a lock where the source has none. Progress is reported from them under a lock.
  Executor* executor = nullptr;
  /// What the import drapes over the model. Every patch gets a texture tile
  /// (Images/Diffuse/<patch>.tif: leaves from the source, parents downsampled from their
  /// children's tiles) and Coordinates.aara, except with Drape::None.
  enum class Drape {
    /// The surface's own shaded relief (shadedRelief: grey, sun from azimuth 315 deg at 45 deg
    /// altitude, no vertical exaggeration), computed per texel from the bottom grids.
    ShadedRelief,
    /// The image `texture`: georeferenced (GDAL reads a geotransform and a CRS) it is placed by
    /// each vertex's geographic position, otherwise stretched over the grid's extent (pixel edge
    /// to pixel edge).
    Image,
    /// No texture, no Images/ and no Coordinates.aara: PRo3D does not open such a model.
    None,
  };
  Drape drape = Drape::ShadedRelief;
  /// The image of Drape::Image (and only then not empty).
  std::filesystem::path texture;
  /// Texels per grid quad side of every tile (a power of two, the tiles (patchSize - 1) times
  /// as many texels a side, at most kMaxTextureTileSize); 0 chooses: for an image, the power of two
  /// that keeps every image pixel (its pixel size against the grid's spacing at the grid's centre,
  /// rounded up past a 5 % tolerance), capped by kMaxTextureTileSize; for the relief, 1. Must be 0
  /// with Drape::None.
  int texelsPerQuad = 0;
  /// Hidden levels (thesis 5.2, core/opc/README.md "Hidden levels"): when above texelsPerQuad's
  /// value (chosen or given), the levels OPC readers see end where the tiles hold this many texels
  /// per quad side (a power of two, tiles within kMaxTextureTileSize): the levels below, down to
  /// the source's full resolution, are named only in a second hierarchy file, and each level above
  /// a hidden one has its children's tiles side by side. 0 (or not above): every level is seen.
  /// Needs a texture.
  int visibleTexelsPerQuad = 0;
};

/// Builds the full pyramid of `source` (bottom patches with one line of overlap, padded with
/// undefined vertices, every overview by reduction, empty patches omitted) and writes it as a new
/// OPC directory `outDir`. Works patch by patch (memory stays a few patches per level, whatever the
/// source size). Writes into a staging directory beside `outDir` and renames it into place only
/// when complete, so no half-written model is ever left at `outDir`.
///
/// Throws Error(Conflict) when outDir exists, Error(InvalidArgument) when the source has no defined
/// sample or the patch size or texelsPerQuad is invalid or `texture` is given exactly when the
/// drape is not Image, Error(NotFound / Corrupt / InvalidArgument) for an unreadable or unplaceable
/// texture, Error(Cancelled), or the source's errors.
Model buildOpc(GridSource& source, const std::filesystem::path& outDir,
               const ImportOptions& options);

/// Removes the staging directories interrupted imports left in `parent` ("<name>.partial-<id>";
/// only those of `target` when it is given): each one whose writer lock nobody holds (its import
/// died; the kernel freed the lock). One that is being written (locked) is left alone. Failures
/// are logged. Returns how many were removed. buildOpc calls it for its target; a server calls it
/// for its data root at start.
std::size_t removeAbandonedImports(const std::filesystem::path& parent,
                                   std::string_view target = {});

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
