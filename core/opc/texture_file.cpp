// Texture tiles through OpenImageIO, in its own module (image_codec.hpp).
#include "core/opc/texture_file.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstring>
#include <fstream>
#include <memory>
#include <string>
#include <string_view>

#include "core/common/error.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/image_codec.hpp"
#include "core/opc/opc_detail.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/stored_file.hpp"
#include "core/opc/validate.hpp"

namespace vsm::core {
namespace fs = std::filesystem;
namespace {

/// Encodes `pixels` (width x height x channels bytes) in the format of `name`'s extension.
std::vector<std::byte> encodeImage(
    const char* name, const std::uint8_t* pixels, int width, int height, int channels,
    const std::vector<std::pair<std::string, std::string>>& text = {}, bool fastPng = false) {
  std::vector<std::byte> bytes;
  std::string error;
  switch (
      image::codec().encode(name, pixels, width, height, channels, text, fastPng, bytes, error)) {
    case image::Codec::Status::Ok:
      return bytes;
    case image::Codec::Status::NoWriter:
      throw Error(ErrorCode::InvalidArgument,
                  std::string("OpenImageIO cannot write the format of '") + name + "': " + error);
    default:
      throw Error(ErrorCode::Internal,
                  std::string("OpenImageIO cannot encode ") + name + ": " + error);
  }
}

using image::Image;

// Texture files are opened only with the readers of the formats OPC textures come in (TIFF and
// DDS as OPC.md names them, PNG and JPEG from other producers), each chosen by name: never
// OpenImageIO's ImageInput::open(path), which picks any reader by extension (a Patch.xml may name
// "x.exr" or "x.mp4") and then tries every reader it has (FFmpeg, OpenEXR, RAW, ...) on a file
// its extension's reader refuses: a large attack surface for hostile files, and slow. A reader
// created by name opens the file itself and falls back to nothing, so OpenImageIO's global
// try_all_readers is left as it is.

/// OpenImageIO's reader for a texture file's extension (any letter case); null for others.
const char* readerForExtension(const fs::path& file) {
  std::string ext = file.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  if (ext == ".tif" || ext == ".tiff") {
    return "tiff";
  }
  if (ext == ".dds") {
    return "dds";
  }
  if (ext == ".png") {
    return "png";
  }
  if (ext == ".jpg" || ext == ".jpeg") {
    return "jpeg";
  }
  return nullptr;
}

/// OpenImageIO's reader for the format `file`'s first bytes announce; null for others.
const char* readerForContent(const fs::path& file) {
  char bytes[8] = {};
  std::ifstream stream(file, std::ios::binary);
  stream.read(bytes, sizeof bytes);
  const std::string_view head(bytes, static_cast<std::size_t>(stream.gcount()));
  const auto startsWith = [&](std::string_view magic) { return head.starts_with(magic); };
  using namespace std::string_view_literals;
  if (startsWith("II*\0"sv) || startsWith("MM\0*"sv)) {
    return "tiff";
  }
  if (startsWith("DDS "sv)) {
    return "dds";
  }
  if (startsWith("\x89PNG\r\n\x1a\n"sv)) {
    return "png";
  }
  if (startsWith("\xFF\xD8\xFF"sv)) {
    return "jpeg";
  }
  return nullptr;
}

/// `file` read with the reader its extension implies, else with the one its first bytes name,
/// refusing before any allocation an image of more than `maxPixels` pixels. Throws
/// Error(NotFound) when it does not exist, Error(Corrupt) when neither reader opens it or it is
/// unusable, too large or does not decode.
Image readImage(const fs::path& file, std::uint64_t maxPixels) {
  std::error_code ec;
  if (!fs::exists(file, ec)) {
    throw Error(ErrorCode::NotFound, "texture '" + file.string() + "' does not exist");
  }
  const image::Codec& codec = image::codec();
  Image image;
  std::string error;
  auto readWith = [&](const char* reader) {
    image = Image{};
    return codec.read(reader, file.string(), maxPixels, image, error);
  };
  using Status = image::Codec::Status;
  const char* byExtension = readerForExtension(file);
  Status status = byExtension != nullptr ? readWith(byExtension) : Status::CannotOpen;
  if (status == Status::CannotOpen) {
    const char* byContent = readerForContent(file);
    if (byContent == nullptr) {
      throw Error(ErrorCode::Corrupt, "texture '" + file.string() +
                                          "' is not a TIFF, DDS, PNG or JPEG image, the formats "
                                          "accepted for textures");
    }
    if (byExtension == nullptr || std::strcmp(byContent, byExtension) != 0) {
      status = readWith(byContent);
    }
  }
  switch (status) {
    case Status::Ok:
      return image;
    case Status::Unusable:
      throw Error(ErrorCode::Corrupt, "texture '" + file.string() + "' has unusable dimensions " +
                                          std::to_string(image.width) + " x " +
                                          std::to_string(image.height) + " x " +
                                          std::to_string(image.fileChannels) + " channels");
    case Status::TooLarge:
      throw Error(ErrorCode::Corrupt,
                  "texture '" + file.string() + "' is " + std::to_string(image.width) + " x " +
                      std::to_string(image.height) + " pixels, more than limits.texture_pixels (" +
                      std::to_string(maxPixels) + ")");
    case Status::CannotDecode:
      throw Error(ErrorCode::Corrupt, "cannot decode texture '" + file.string() + "': " + error);
    default:
      throw Error(ErrorCode::Corrupt, "cannot read texture '" + file.string() + "': " + error);
  }
}

}  // namespace

void loadImageCodec() {
  image::codec();
}

std::vector<std::byte> encodeImageFile(const std::string& name, const std::uint8_t* rgba, int width,
                                       int height) {
  return encodeImage(name.c_str(), rgba, width, height, 4);
}

std::vector<std::byte> encodePng(const std::uint8_t* pixels, int width, int height, int channels,
                                 const std::vector<std::pair<std::string, std::string>>& text,
                                 PngCompression compression) {
  return encodeImage("image.png", pixels, width, height, channels, text,
                     compression == PngCompression::Fast);
}

TextureTile readTextureTile(const fs::path& file, std::uint64_t maxPixels) {
  const Image image = readImage(file, maxPixels);
  const int width = image.width;
  const int channels = image.channels;
  if (width != image.height || width % 2 != 0) {
    throw Error(ErrorCode::Corrupt, "texture '" + file.string() + "' is " + std::to_string(width) +
                                        " x " + std::to_string(image.height) +
                                        ", not a square tile of even size");
  }
  TextureTile tile(width);
  std::uint8_t* out = tile.texels().data();
  for (std::size_t i = 0; i < static_cast<std::size_t>(width) * width; ++i) {
    const std::uint8_t* p = image.pixels.data() + i * channels;
    const bool gray = channels < 3;
    out[4 * i] = p[0];
    out[4 * i + 1] = gray ? p[0] : p[1];
    out[4 * i + 2] = gray ? p[0] : p[2];
    out[4 * i + 3] = channels == 2 ? p[1] : channels == 4 ? p[3] : 255;
  }
  return tile;
}

namespace {

/// The texture tile file a patch names; throws Error(NotFound) as readPatchTextureTile.
fs::path textureFileOf(const fs::path& dir, const PatchInfo& info) {
  const auto file =
      info.textureFile().empty() ? std::nullopt : detail::findTextureFile(dir, info.textureFile());
  if (!file) {
    throw Error(ErrorCode::NotFound,
                "patch " + info.folder() + " has no texture tile" +
                    (info.textureFile().empty() ? std::string()
                                                : " ('" + info.textureFile() + "' is missing)"));
  }
  return *file;
}

/// The image of the tile a patch names, as it is (at most 4 channels: the served forms hold no
/// more); throws as readPatchTexturePng.
Image readPatchImage(const fs::path& dir, const PatchInfo& info, std::uint64_t maxPixels) {
  const fs::path file = textureFileOf(dir, info);
  Image image = readImage(file, maxPixels);
  if (image.fileChannels > 4) {
    throw Error(ErrorCode::Corrupt, "texture '" + file.string() + "' has more than 4 channels");
  }
  return image;
}

/// The tile for a glTF: JPEG (quality 90) where no texel is transparent, the alpha channel left
/// out; else PNG, the image as it is.
void encodeForGlb(const Image& image, PatchTexture& texture) {
  const int channels = image.channels;
  const std::size_t texels = static_cast<std::size_t>(image.width) * image.height;
  bool opaque = true;
  if (channels == 2 || channels == 4) {
    for (std::size_t i = 0; i < texels && opaque; ++i) {
      opaque = image.pixels[i * channels + channels - 1] == 255;
    }
  }
  if (!opaque) {
    texture.image =
        encodeImage("tile.png", image.pixels.data(), image.width, image.height, channels);
    texture.mimeType = "image/png";
    return;
  }
  const int colours = channels < 3 ? 1 : 3;
  std::vector<std::uint8_t> pixels;
  const std::uint8_t* data = image.pixels.data();
  if (colours != channels) {
    pixels.resize(texels * colours);
    for (std::size_t i = 0; i < texels; ++i) {
      std::copy_n(image.pixels.data() + i * channels, colours, pixels.data() + i * colours);
    }
    data = pixels.data();
  }
  texture.image = encodeImage("tile.jpg", data, image.width, image.height, colours,
                              {{"Compression", "jpeg:90"}});
  texture.mimeType = "image/jpeg";
}

}  // namespace

TextureTile readPatchTextureTile(const fs::path& dir, const PatchInfo& info,
                                 std::uint64_t maxPixels) {
  return readTextureTile(textureFileOf(dir, info), maxPixels);
}

std::vector<std::byte> readPatchTexturePng(const fs::path& dir, const PatchInfo& info,
                                           std::uint64_t maxPixels) {
  const Image image = readPatchImage(dir, info, maxPixels);
  // PNG holds 1 to 4 channels of 8 bits: the image as it is.
  return encodeImage("tile.png", image.pixels.data(), image.width, image.height, image.channels);
}

std::vector<std::byte> readPatchCoordinates(const fs::path& dir, const PatchInfo& info) {
  return readStoredFile(*openCoordinatesFile(dir, info), info.coordinatesFile());
}

std::optional<PatchTexture> readPatchTexture(const fs::path& dir, const Model& model,
                                             const PatchInfo& info, std::uint64_t maxPixels) {
  if (info.textureFile().empty()) {
    return std::nullopt;
  }
  PatchTexture texture;
  encodeForGlb(readPatchImage(dir, info, maxPixels), texture);

  const int n = model.gridSize();
  const GridRect& r = info.stored;
  texture.texcoords.assign(static_cast<std::size_t>(n) * n * 2, 0.0f);
  if (info.coordinatesFile().empty()) {
    // A texture without coordinates: the tile stretched over the grid.
    for (int y = 0; y < n; ++y) {
      for (int x = 0; x < n; ++x) {
        texture.texcoords[(static_cast<std::size_t>(y) * n + x) * 2] = textureCoordinate(x, n);
        texture.texcoords[(static_cast<std::size_t>(y) * n + x) * 2 + 1] = textureCoordinate(y, n);
      }
    }
    return texture;
  }
  const AaraArray array = decodeAara(readPatchCoordinates(dir, info), info.coordinatesFile());
  const std::size_t count = static_cast<std::size_t>(r.width()) * r.height();
  for (std::size_t i = 0; i < count; ++i) {
    float uv[2];
    if (array.type == AaraType::V2f) {
      std::memcpy(uv, array.data.data() + i * 8, 8);
    } else {
      double d[2];
      std::memcpy(d, array.data.data() + i * 16, 16);
      uv[0] = static_cast<float>(d[0]);
      uv[1] = static_cast<float>(d[1]);
    }
    const int x = r.x0 + static_cast<int>(i % r.width());
    const int y = r.y0 + static_cast<int>(i / r.width());
    const std::size_t at = (static_cast<std::size_t>(y) * n + x) * 2;
    // glTF forbids non-finite accessor values.
    texture.texcoords[at] = std::isfinite(uv[0]) ? uv[0] : 0.0f;
    texture.texcoords[at + 1] = std::isfinite(uv[1]) ? uv[1] : 0.0f;
  }
  return texture;
}

}  // namespace vsm::core
