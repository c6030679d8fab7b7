// libvsm_image.so: OpenImageIO behind image::Codec (image_codec.hpp says why it is a module).
#include <OpenImageIO/filesystem.h>
#include <OpenImageIO/imageio.h>

#include <cstring>
#include <memory>
#include <string>

#include "core/opc/image_codec.hpp"

namespace vsm::core::image {

namespace {

class OiioCodec final : public Codec {
 public:
  Status encode(const char* name, const std::uint8_t* pixels, int width, int height, int channels,
                const std::vector<std::pair<std::string, std::string>>& text, bool fastPng,
                std::vector<std::byte>& out, std::string& error) const override {
    std::vector<unsigned char> buffer;
    OIIO::Filesystem::IOVecOutput proxy(buffer);
    std::unique_ptr<OIIO::ImageOutput> output = OIIO::ImageOutput::create(name);
    if (!output || !output->supports("ioproxy")) {
      error = OIIO::geterror();
      return Status::NoWriter;
    }
    OIIO::ImageSpec spec(width, height, channels, OIIO::TypeDesc::UINT8);
    // OpenImageIO stamps a TIFF with the time it is written unless told a time: the same texels
    // must give the same bytes (imports in parallel, re-imports, a restore compared with its
    // revision).
    spec.attribute("DateTime", "");
    for (const auto& [keyword, value] : text) {
      spec.attribute(keyword, value);
    }
    if (fastPng) {
      // Ints: the PNG writer reads them and, unlike string attributes, writes no text chunk of
      // them. zlib level 1 and libpng's Sub filter alone (PNG_FILTER_SUB) instead of trying all
      // five per row.
      spec.attribute("png:compressionLevel", 1);
      spec.attribute("png:filter", 0x10);
    }
    output->set_ioproxy(&proxy);
    if (!output->open(name, spec) || !output->write_image(OIIO::TypeDesc::UINT8, pixels) ||
        !output->close()) {
      error = output->geterror();
      return Status::CannotEncode;
    }
    out.resize(buffer.size());
    std::memcpy(out.data(), buffer.data(), buffer.size());
    return Status::Ok;
  }

  Status read(const char* reader, const std::string& file, std::uint64_t maxPixels, Image& image,
              std::string& error) const override {
    // A reader created by name opens the file itself and falls back to nothing, so OpenImageIO's
    // global try_all_readers is left as it is (texture_file.cpp says why).
    std::unique_ptr<OIIO::ImageInput> in = OIIO::ImageInput::create(reader);
    if (!in) {
      error = std::string("OpenImageIO has no ") + reader + " reader: " + OIIO::geterror();
      return Status::CannotOpen;
    }
    OIIO::ImageSpec opened;
    if (!in->open(file, opened)) {
      error = in->geterror();
      return Status::CannotOpen;
    }
    const OIIO::ImageSpec& spec = in->spec();
    image.width = spec.width;
    image.height = spec.height;
    image.fileChannels = spec.nchannels;
    image.channels = std::min(spec.nchannels, 4);
    if (image.width < 1 || image.height < 1 || image.channels < 1) {
      return Status::Unusable;
    }
    const std::uint64_t pixels = static_cast<std::uint64_t>(image.width) * image.height;
    if (pixels > maxPixels) {
      return Status::TooLarge;
    }
    image.pixels.resize(static_cast<std::size_t>(pixels) * image.channels);
    // An 8-bit file is read as it is (TypeDesc::UNKNOWN): OpenImageIO 2.4 converts any other
    // request through a buffer of about 64 MB, whatever the image's size.
    const bool eightBit = spec.format == OIIO::TypeDesc::UINT8 && spec.channelformats.empty();
    const OIIO::TypeDesc format = eightBit ? OIIO::TypeDesc::UNKNOWN : OIIO::TypeDesc::UINT8;
    if (!in->read_image(0, 0, 0, image.channels, format, image.pixels.data())) {
      error = in->geterror();
      return Status::CannotDecode;
    }
    return Status::Ok;
  }
};

}  // namespace

}  // namespace vsm::core::image

extern "C" __attribute__((visibility("default"))) const vsm::core::image::Codec* vsm_image_codec() {
  static const vsm::core::image::OiioCodec codec;
  return &codec;
}
