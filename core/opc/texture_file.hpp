#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "core/grid/texture_tile.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

/// The layer (folder under Images/) of the texture tiles vsm writes.
inline constexpr std::string_view kTextureLayer = "Diffuse";

/// Loads OpenImageIO's module (core/opc/image_codec.hpp) now; otherwise the first texture file
/// read or written loads it, which takes ~0.45 s. For a caller that will need it and can load it
/// on a thread of its own meanwhile. Throws Error(Internal) when it cannot be loaded.
void loadImageCodec();

/// A tile as an 8-bit TIFF file: RGB when every texel is opaque, else RGBA (associated alpha);
/// strips of 32 rows, deflate level 1 with the horizontal predictor; written with libtiff
/// (tiff_tile.cpp). Throws Error(Internal) when libtiff fails.
std::vector<std::byte> encodeTextureTiff(const TextureTile& tile);

/// How hard a PNG is compressed: OpenImageIO's defaults (zlib level 6, libpng choosing a filter
/// per row), or Fast (level 1, the Sub filter). On terrain-RGB tiles of Jacksboro (256 x 256 RGB)
/// Fast made a cold tile's answer 2.2x faster (10.5 -> 4.6 ms median over 176 tiles, HTTP
/// included) for files 23 % larger (tests/bench/results/terrain-rgb.txt).
enum class PngCompression : std::uint8_t { Default, Fast };

/// An 8-bit image of `channels` channels (1..4: grey, grey and alpha, RGB, RGBA; width x height x
/// channels bytes, top row first) as a PNG file, with `text` as (keyword, value) text chunks.
/// Throws Error(Internal) when OpenImageIO cannot encode it.
std::vector<std::byte> encodePng(const std::uint8_t* pixels, int width, int height, int channels,
                                 const std::vector<std::pair<std::string, std::string>>& text = {},
                                 PngCompression compression = PngCompression::Default);

/// An RGBA 8-bit image (as encodePng) as a file of the format `name`'s extension names (".png",
/// ".tif", ".jpg": any OpenImageIO writes to memory). Throws Error(InvalidArgument) when it writes
/// no such format, Error(Internal) when encoding fails.
std::vector<std::byte> encodeImageFile(const std::string& name, const std::uint8_t* rgba, int width,
                                       int height);

/// The default bound on the pixels of a texture file a reader decodes (16384 x 16384), the
/// configuration's limits.texture_pixels: a file's header may claim any size.
inline constexpr std::uint64_t kDefaultTexturePixels = std::uint64_t{16384} * 16384;

/// Decodes a texture file (our TIFF tiles, foreign TIFF, DDS, PNG or JPEG) into a tile.
/// Only OpenImageIO's readers of those four formats are used: the one the extension implies
/// (.tif/.tiff, .dds, .png, .jpg/.jpeg, any letter case), else the one the first bytes name (a
/// PNG named .tif reads); a file of any other format is refused, whatever the extension. The size
/// in the file's header is checked before any pixel is allocated. Throws Error(NotFound) when the
/// file does not exist, Error(Corrupt) when it is of no accepted format, cannot be decoded, is not
/// a square tile of even size, or has more than `maxPixels` pixels. 1, 2 and 3 channel images get
/// alpha 255; channels after the 4th are ignored.
TextureTile readTextureTile(const std::filesystem::path& file,
                            std::uint64_t maxPixels = kDefaultTexturePixels);

/// The texture tile a patch of the OPC at `dir` names (info.textureFile()). Throws
/// Error(NotFound) when the patch names none or the file is missing, Error(Corrupt) as
/// readTextureTile.
TextureTile readPatchTextureTile(const std::filesystem::path& dir, const PatchInfo& info,
                                 std::uint64_t maxPixels = kDefaultTexturePixels);

/// The texture tile a patch names, as a PNG file (the image as stored: 1 to 4 channels of 8 bits).
/// Throws as readPatchTextureTile, and Error(Corrupt) for more than 4 channels.
std::vector<std::byte> readPatchTexturePng(const std::filesystem::path& dir, const PatchInfo& info,
                                           std::uint64_t maxPixels = kDefaultTexturePixels);

/// The bytes of the texture coordinates file (.aara) a patch names, as stored, once checked: V2f or
/// V2d of the stored positions' size. Throws Error(NotFound) when it names none or the file does
/// not exist, Error(Corrupt) when it does not decode so.
std::vector<std::byte> readPatchCoordinates(const std::filesystem::path& dir,
                                            const PatchInfo& info);

/// The texture of one patch, ready for a GLB.
struct PatchTexture {
  /// The tile as a JPEG file (quality 90, without alpha) when every texel is opaque, else as a
  /// PNG file: `mimeType` says which.
  std::vector<std::byte> image;
  std::string mimeType;
  /// (u, v) per vertex of the full gridSize x gridSize grid (cropped borders: 0), as
  /// GlbOptions::texcoords wants them.
  std::vector<float> texcoords;
};

/// Reads the texture of a patch of the OPC at `dir` (its tile converted to JPEG or PNG through
/// OpenImageIO and its Coordinates.aara expanded to the full grid); nullopt when `info` names no
/// texture. Throws Error(NotFound) when a named file is missing, Error(Corrupt) when it cannot be
/// decoded, when the coordinates are not V2f/V2d of the stored positions' size.
std::optional<PatchTexture> readPatchTexture(const std::filesystem::path& dir, const Model& model,
                                             const PatchInfo& info,
                                             std::uint64_t maxPixels = kDefaultTexturePixels);

}  // namespace vsm::core
