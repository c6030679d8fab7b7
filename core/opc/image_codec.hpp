#pragma once
// The seam between vsm and OpenImageIO. OpenImageIO links ~260 shared libraries (OpenCV, FFmpeg,
// DICOM, ...) that took ld.so 0.45 s to load and initialise on every start of a binary linking it
// (tests/bench/startup_bench.sh), whether or not it touched an image. Its code therefore lives in
// a module of its own, libvsm_image.so (image_oiio.cpp), loaded with dlopen on the first image
// read or written: `vsm merge`, vsmd and the tests start without it.
//
// Only standard types cross the seam (no vsm::core::Error: the module keeps its own copy of what
// it links), so the module reports failures as a Status and a message, and this side throws.

#include <cstddef>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

namespace vsm::core::image {

/// The first subimage of an image file as 8-bit pixels, at most 4 channels of it.
struct Image {
  int width = 0;
  int height = 0;
  /// Channels in `pixels`: min(fileChannels, 4).
  int channels = 0;
  int fileChannels = 0;
  std::vector<std::uint8_t> pixels;
};

class Codec {
 public:
  enum class Status {
    Ok,
    /// read: the reader cannot open the file (not its format, or its header is broken).
    CannotOpen,
    /// read: width, height or channels below 1 (Image's fields say what the header said).
    Unusable,
    /// read: more than `maxPixels` pixels (width and height set); nothing was allocated.
    TooLarge,
    /// read: the pixels do not decode.
    CannotDecode,
    /// encode: OpenImageIO has no writer (to memory) for the format.
    NoWriter,
    /// encode: the writer failed.
    CannotEncode,
  };

  /// Encodes `pixels` (width x height x channels bytes, top row first) in the format of `name`'s
  /// extension ("image.png", "lod.tif"), in memory, with (keyword, value) metadata, into `out`.
  /// `fastPng`: a PNG compressed fast (zlib level 1, the Sub filter) rather than at OpenImageIO's
  /// defaults (level 6, libpng's choice of filter per row); other formats ignore it.
  virtual Status encode(const char* name, const std::uint8_t* pixels, int width, int height,
                        int channels, const std::vector<std::pair<std::string, std::string>>& text,
                        bool fastPng, std::vector<std::byte>& out, std::string& error) const = 0;

  /// Reads `file` with OpenImageIO's reader `reader` alone ("tiff", "dds", "png", "jpeg"; never
  /// another one it would try after a failure), into `out`, refusing before any allocation an image
  /// of more than `maxPixels` pixels.
  virtual Status read(const char* reader, const std::string& file, std::uint64_t maxPixels,
                      Image& out, std::string& error) const = 0;

 protected:
  ~Codec() = default;
};

/// The codec: the module loaded on the first call (later calls wait for it, then return at
/// once). The module is libvsm_image.so, found as dlopen finds libraries (the build tree through
/// the binaries' RUNPATH, an installation in /usr/local/lib), or at $VSM_IMAGE_MODULE. Throws
/// Error(Internal) naming the module and dlopen's message when it cannot be loaded; a later call
/// tries again.
const Codec& codec();

}  // namespace vsm::core::image

/// What the module exports (the one symbol looked up); a binary may also link image_oiio.cpp in
/// (the fuzz targets do), and codec() then uses it without loading anything.
extern "C" const vsm::core::image::Codec* vsm_image_codec();
