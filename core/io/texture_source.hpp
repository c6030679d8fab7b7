#pragma once

// Internal to core/io (and its tests): the image an import drapes over its grid.

#include <filesystem>
#include <memory>
#include <optional>
#include <string>

#include "core/grid/patch_grid.hpp"
#include "core/grid/texture_tile.hpp"
#include "core/io/grid_source.hpp"

namespace vsm::core {

/// What an import drapes over its grid, bottom patch by bottom patch (the builder downsamples the
/// parents' tiles from their children's). Thread-safe: builders of disjoint subtrees call
/// fillTile concurrently.
class TileSource {
 public:
  virtual ~TileSource() = default;
  /// One line for logs.
  virtual std::string describe() const = 0;
  /// The texels per grid quad side that keep the source's detail on patches of `patchSize`
  /// vertices (ImportOptions::texelsPerQuad's choice).
  virtual int naturalTexelsPerQuad(int patchSize) const = 0;
  /// Fills the tile of the bottom patch `grid` whose vertex (0, 0) is grid sample (x0, y0), with
  /// f = tile.size() / (grid.size() - 1) texels per quad side: texel (i, j) covers the part of the
  /// patch between vertex coordinates (i / f, j / f) and ((i + 1) / f, (j + 1) / f).
  /// Throws Error(Io / Corrupt) when the source cannot be read.
  virtual void fillTile(int x0, int y0, const PatchGrid& grid, TextureTile& tile) const = 0;
};

/// The shaded relief of the surface itself (shadedRelief), for imports without an image.
/// One texel per quad is its nature (a finer tile is the relief upsampled: resizeTile).
class ShadedReliefSource final : public TileSource {
 public:
  std::string describe() const override;
  int naturalTexelsPerQuad(int /*patchSize*/) const override { return 1; }
  void fillTile(int x0, int y0, const PatchGrid& grid, TextureTile& tile) const override;
};

/// An image placed over a grid of gridWidth x gridHeight samples, read through GDAL.
///
/// Placement: when the image has a geotransform and a CRS and the grid a georeference, a point of
/// the grid (sample coordinates, pixel centres at integers) goes to its geographic position in the
/// grid's CRS, through OGR to the image's CRS, and through the image's inverse geotransform to
/// image pixels. Otherwise the image is stretched over the grid's extent, pixel edge to pixel
/// edge: grid edge coordinate e in [0, gridWidth] maps to image edge coordinate e * imageWidth /
/// gridWidth (rows alike). Colours are bilinear between image pixel centres; points outside the
/// image are transparent.
///
/// Thread-safe: the GDAL dataset and the OGR transformation are used under an internal lock, the
/// sampling runs outside it.
class TextureSource final : public TileSource {
 public:
  /// Throws Error(NotFound) when `image` does not exist, Error(Corrupt) when GDAL cannot read it,
  /// Error(InvalidArgument) when it has no band or its CRS cannot be reached from the grid's.
  TextureSource(const std::filesystem::path& image, int gridWidth, int gridHeight,
                const std::optional<Georeference>& grid);
  ~TextureSource();
  TextureSource(const TextureSource&) = delete;
  TextureSource& operator=(const TextureSource&) = delete;

  /// "'<image>': GTiff 333x147 3 bands, EPSG:4326, georeferenced" or "... stretched".
  std::string describe() const override;
  bool georeferenced() const;

  /// Image pixel coordinates (pixel-edge convention: (0, 0) the top left corner of the image) of
  /// grid point (gx, gy) (sample coordinates). nullopt when the point cannot be transformed.
  std::optional<std::pair<double, double>> imagePoint(double gx, double gy) const;

  /// The image's pixels per grid sample at the grid's centre (the longer of its steps along the
  /// grid's rows and columns); nullopt when that point cannot be placed on the image.
  std::optional<double> pixelsPerSample() const;
  /// The power of two f with f >= pixelsPerSample() / 1.05, capped where the tile would exceed
  /// kMaxTextureTileSize; 1 when the centre cannot be placed.
  int naturalTexelsPerQuad(int patchSize) const override;

  /// Texel (i, j) takes the colour at grid point (x0 + (i + 0.5) / f, y0 + (j + 0.5) / f), the
  /// centre of the part of the patch it covers (the grid's positions are not used). Where the
  /// image is finer than the texels GDAL first averages it to at most twice their resolution.
  /// Throws Error(Io / Corrupt) when the image cannot be read.
  void fillTile(int x0, int y0, const PatchGrid& grid, TextureTile& tile) const override;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace vsm::core
