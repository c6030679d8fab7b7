// Texture tiles as TIFF files, written with libtiff itself rather than through OpenImageIO.
//
// Why: an import writes one tile per patch, and compressing them was a fifth of its CPU time.
// OpenImageIO hands libtiff one scanline at a time, so libtiff compresses with zlib; given a whole
// strip it uses libdeflate (Debian's libtiff links it), about 3x faster at the same level. Writing
// here also keeps OpenImageIO's module out of imports and merges that only write tiles.
#include <tiffio.h>

#include <algorithm>
#include <cstdarg>
#include <cstdio>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/opc/texture_file.hpp"

namespace vsm::core {
namespace {

/// The file libtiff writes, in memory.
struct MemoryFile {
  std::vector<std::byte> bytes;
  std::size_t position = 0;
  std::string error;  // libtiff's last error message
};

MemoryFile& fileOf(thandle_t handle) {
  return *static_cast<MemoryFile*>(handle);
}

tmsize_t readBytes(thandle_t handle, void* data, tmsize_t size) {
  MemoryFile& file = fileOf(handle);
  const std::size_t available =
      file.position < file.bytes.size() ? file.bytes.size() - file.position : 0;
  const std::size_t n = std::min(available, static_cast<std::size_t>(size));
  std::memcpy(data, file.bytes.data() + file.position, n);
  file.position += n;
  return static_cast<tmsize_t>(n);
}

tmsize_t writeBytes(thandle_t handle, void* data, tmsize_t size) {
  MemoryFile& file = fileOf(handle);
  const std::size_t end = file.position + static_cast<std::size_t>(size);
  if (end > file.bytes.size()) {
    file.bytes.resize(end);
  }
  std::memcpy(file.bytes.data() + file.position, data, static_cast<std::size_t>(size));
  file.position = end;
  return size;
}

toff_t seekTo(thandle_t handle, toff_t offset, int whence) {
  MemoryFile& file = fileOf(handle);
  const std::size_t base = whence == SEEK_CUR   ? file.position
                           : whence == SEEK_END ? file.bytes.size()
                                                : 0;
  file.position = base + static_cast<std::size_t>(offset);
  return file.position;
}

int closeFile(thandle_t) {
  return 0;
}

toff_t sizeOf(thandle_t handle) {
  return fileOf(handle).bytes.size();
}

int noMap(thandle_t, void**, toff_t*) {
  return 0;
}

void noUnmap(thandle_t, void*, toff_t) {}

int recordError(TIFF*, void* handle, const char* module, const char* format, va_list args) {
  char message[512];
  std::vsnprintf(message, sizeof message, format, args);
  static_cast<MemoryFile*>(handle)->error =
      std::string(module ? module : "libtiff") + ": " + message;
  return 1;  // handled: nothing on stderr
}

int ignoreWarning(TIFF*, void*, const char*, const char*, va_list) {
  return 1;
}

struct OptionsDeleter {
  void operator()(TIFFOpenOptions* options) const { TIFFOpenOptionsFree(options); }
};

}  // namespace

std::vector<std::byte> encodeTextureTiff(const TextureTile& tile) {
  constexpr int kRowsPerStrip = 32;
  MemoryFile file;
  const std::unique_ptr<TIFFOpenOptions, OptionsDeleter> options(TIFFOpenOptionsAlloc());
  TIFFOpenOptionsSetErrorHandlerExtR(options.get(), recordError, &file);
  TIFFOpenOptionsSetWarningHandlerExtR(options.get(), ignoreWarning, nullptr);
  TIFF* tiff = TIFFClientOpenExt("tile.tif", "w", &file, readBytes, writeBytes, seekTo, closeFile,
                                 sizeOf, noMap, noUnmap, options.get());
  const auto fail = [&file]() -> Error {
    return Error(ErrorCode::Internal, "cannot encode a texture tile as TIFF: " +
                                          (file.error.empty() ? "libtiff failed" : file.error));
  };
  if (tiff == nullptr) {
    throw fail();
  }
  const int size = tile.size();
  // An opaque tile (every texel's alpha 255: most of them) goes without its alpha channel, a
  // quarter less to compress and to store; a grey one (the shaded relief) as one channel, a third
  // of RGB (PRo3D's loader reads it as luminance and its renderer shows it grey).
  const int channels = tile.storedChannels();
  const bool opaque = channels < TextureTile::kChannels;
  const std::uint16_t extra[] = {EXTRASAMPLE_ASSOCALPHA};
  const std::size_t rowBytes = static_cast<std::size_t>(size) * channels;
  bool ok = TIFFSetField(tiff, TIFFTAG_IMAGEWIDTH, size) == 1 &&
            TIFFSetField(tiff, TIFFTAG_IMAGELENGTH, size) == 1 &&
            TIFFSetField(tiff, TIFFTAG_BITSPERSAMPLE, 8) == 1 &&
            TIFFSetField(tiff, TIFFTAG_SAMPLESPERPIXEL, channels) == 1 &&
            (opaque || TIFFSetField(tiff, TIFFTAG_EXTRASAMPLES, 1, extra) == 1) &&
            TIFFSetField(tiff, TIFFTAG_SAMPLEFORMAT, SAMPLEFORMAT_UINT) == 1 &&
            TIFFSetField(tiff, TIFFTAG_PHOTOMETRIC,
                         channels == 1 ? PHOTOMETRIC_MINISBLACK : PHOTOMETRIC_RGB) == 1 &&
            TIFFSetField(tiff, TIFFTAG_PLANARCONFIG, PLANARCONFIG_CONTIG) == 1 &&
            TIFFSetField(tiff, TIFFTAG_ORIENTATION, ORIENTATION_TOPLEFT) == 1 &&
            TIFFSetField(tiff, TIFFTAG_ROWSPERSTRIP, kRowsPerStrip) == 1 &&
            TIFFSetField(tiff, TIFFTAG_COMPRESSION, COMPRESSION_ADOBE_DEFLATE) == 1 &&
            TIFFSetField(tiff, TIFFTAG_ZIPQUALITY, 1) == 1 &&
            TIFFSetField(tiff, TIFFTAG_PREDICTOR, PREDICTOR_HORIZONTAL) == 1;
  // One call per whole strip, which is what makes libtiff use libdeflate. The predictor works on
  // a copy: the tile is left as it is.
  const std::uint8_t* texels = tile.texels().data();
  std::vector<std::uint8_t> rgb(opaque ? rowBytes * kRowsPerStrip : 0);
  for (int row = 0, strip = 0; ok && row < size; row += kRowsPerStrip, ++strip) {
    const int rows = std::min(kRowsPerStrip, size - row);
    const std::uint8_t* data = texels + rowBytes * row;
    if (opaque) {
      const std::uint8_t* from = texels + static_cast<std::size_t>(row) * size * 4;
      const std::size_t count = static_cast<std::size_t>(rows) * size;
      if (channels == 1) {
        for (std::size_t i = 0; i < count; ++i) {
          rgb[i] = from[4 * i];
        }
      } else {
        for (std::size_t i = 0; i < count; ++i) {
          std::memcpy(rgb.data() + 3 * i, from + 4 * i, 3);
        }
      }
      data = rgb.data();
    }
    ok = TIFFWriteEncodedStrip(tiff, static_cast<std::uint32_t>(strip),
                               const_cast<std::uint8_t*>(data),
                               static_cast<tmsize_t>(rowBytes * rows)) >= 0;
  }
  ok = ok && TIFFWriteDirectory(tiff) == 1;
  TIFFClose(tiff);
  if (!ok) {
    throw fail();
  }
  return std::move(file.bytes);
}

}  // namespace vsm::core
