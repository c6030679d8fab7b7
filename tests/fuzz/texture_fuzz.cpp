// Fuzz target: texture file reading through our OpenImageIO wrapper (readTextureTile, the PNG
// conversion the texture route sends and the JPEG or PNG a GLB carries), with a pixel limit: what a
// file's header claims is checked before pixels are allocated. Inputs are written to
// Images/Diffuse/tile.tif: OpenImageIO's TIFF reader sees every input, and when it refuses one, the
// DDS, PNG or JPEG reader sees it if its first bytes are of that format; no other reader is ever
// tried (other formats are refused).
#include <cstddef>
#include <cstdint>
#include <vector>

#include "core/opc/texture_file.hpp"
#include "tests/fuzz/fuzz_support.hpp"

using namespace vsm;
namespace fs = std::filesystem;

namespace {

/// Small enough that a claim just under it stays far below -malloc_limit_mb: 4 bytes x 2^22.
constexpr std::uint64_t kMaxPixels = std::uint64_t{1} << 22;

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const fuzz::ScratchDir scratch("texture");
  static const fs::path file = [] {
    fs::create_directories(scratch.path() / "Images" / "Diffuse");
    return scratch.path() / "Images" / "Diffuse" / "tile.tif";
  }();
  fuzz::writeFile(file, data, size);

  fuzz::succeeds([&] {
    const core::TextureTile tile = core::readTextureTile(file, kMaxPixels);
    fuzz::check(static_cast<std::uint64_t>(tile.size()) * tile.size() <= kMaxPixels,
                "a tile read is within the pixel limit");
  });
  core::PatchInfo info;
  info.setFiles({"Positions.aara", "", "Diffuse\\tile.tif"});
  fuzz::succeeds([&] {
    const std::vector<std::byte> png = core::readPatchTexturePng(scratch.path(), info, kMaxPixels);
    fuzz::check(png.size() >= 8, "a PNG has its signature");
  });
  // The GLB's form: JPEG where every texel is opaque, else PNG.
  static const core::Model model(5);
  info.stored = core::GridRect{0, 0, 5, 5};
  fuzz::succeeds([&] {
    const auto texture = core::readPatchTexture(scratch.path(), model, info, kMaxPixels);
    fuzz::check(texture && texture->image.size() >= 8 &&
                    (texture->mimeType == "image/jpeg" || texture->mimeType == "image/png"),
                "a GLB texture is a JPEG or a PNG");
  });
  return 0;
}
