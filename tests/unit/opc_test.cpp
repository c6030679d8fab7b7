#include <gtest/gtest.h>
#include <unistd.h>

#include <pugixml.hpp>

#include <array>
#include <cmath>
#include <cstring>
#include <fstream>
#include <map>
#include <random>
#include <sstream>
#include <string_view>

#include "core/common/error.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/image_codec.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/stored_file.hpp"
#include "core/opc/texture_file.hpp"
#include "core/opc/validate.hpp"
#include "core/opc/xml_writer.hpp"
#include "tests/unit/test_support.hpp"

namespace fs = std::filesystem;

namespace vsm::core {
namespace {

using test::codeOf;
using test::filesUnder;
using test::messageOf;

std::vector<std::byte> bytesOf(std::initializer_list<int> values) {
  std::vector<std::byte> out;
  for (const int v : values) {
    out.push_back(static_cast<std::byte>(v));
  }
  return out;
}

void appendFloat(std::vector<std::byte>& out, float f) {
  unsigned char b[4];
  std::memcpy(b, &f, 4);  // the test host is little-endian, as the format
  for (const unsigned char c : b) {
    out.push_back(static_cast<std::byte>(c));
  }
}

/// OPC.md's example: a V3f grid of 3 x 2 with vertex (1, 1) undefined, 85 bytes.
std::vector<std::byte> specExample() {
  std::vector<std::byte> bytes = bytesOf({0x03, 'V', '3', 'f', 0x02, 3, 0, 0, 0, 2, 0, 0, 0});
  const float nan = std::nanf("");
  for (const float f : {0.f, 0.f, 0.f, 1.f, 0.f, 0.f, 2.f, 0.f, 0.5f, 0.f, 1.f, 0.f, nan, nan, nan,
                        2.f, 1.f, 0.25f}) {
    appendFloat(bytes, f);
  }
  return bytes;
}

TEST(Aara, DecodesTheSpecExample) {
  const std::vector<std::byte> bytes = specExample();
  ASSERT_EQ(bytes.size(), 85u);
  const AaraArray array = decodeAara(bytes, "example");
  EXPECT_EQ(array.type, AaraType::V3f);
  EXPECT_EQ(array.sizes, (std::vector<std::int32_t>{3, 2}));
  ASSERT_EQ(array.data.size(), 72u);
  float v[3];
  std::memcpy(v, array.data.data() + 5 * 12, 12);  // (2, 1)
  EXPECT_EQ(v[0], 2.f);
  EXPECT_EQ(v[2], 0.25f);
  std::memcpy(v, array.data.data() + 4 * 12, 12);  // (1, 1)
  EXPECT_TRUE(std::isnan(v[0]));
  EXPECT_EQ(encodeAara(array), bytes);
}

TEST(Aara, EveryTypeNameAndSizeIsTheSpecs) {
  const std::map<std::string, std::size_t> spec{
      {"byte", 1}, {"int", 4},  {"float", 4}, {"double", 8}, {"V2f", 8},  {"V3f", 12},
      {"V2d", 16}, {"V3d", 24}, {"C3b", 3},   {"C4b", 4},    {"C3f", 12}, {"C4f", 16}};
  for (const auto& [name, size] : spec) {
    const auto type = parseAaraType(name);
    ASSERT_TRUE(type) << name;
    EXPECT_EQ(elementSize(*type), size) << name;
    EXPECT_EQ(toString(*type), name);
  }
  EXPECT_FALSE(parseAaraType("v3f"));  // names are exact
  EXPECT_FALSE(parseAaraType("V4f"));
}

TEST(Aara, CorruptInputsAreRejectedWithAClearMessage) {
  const std::vector<std::byte> good = specExample();
  auto truncated = good;
  truncated.resize(good.size() - 5);
  EXPECT_NE(messageOf([&] { decodeAara(truncated, "f.aara"); }).find("truncated"),
            std::string::npos);
  auto trailing = good;
  trailing.push_back(std::byte{0});
  EXPECT_NE(messageOf([&] { decodeAara(trailing, "f.aara"); }).find("trailing"), std::string::npos);
  auto dims = good;
  dims[4] = std::byte{7};
  EXPECT_NE(messageOf([&] { decodeAara(dims, "f.aara"); }).find("dimension"), std::string::npos);
  auto zeroDims = good;
  zeroDims[4] = std::byte{0};
  EXPECT_EQ(codeOf([&] { decodeAara(zeroDims, "f.aara"); }), ErrorCode::Corrupt);
  auto type = good;
  type[2] = std::byte{'9'};
  const std::string message = messageOf([&] { decodeAara(type, "f.aara"); });
  EXPECT_NE(message.find("V9f"), std::string::npos);
  EXPECT_NE(message.find("f.aara"), std::string::npos);
  auto negative = good;
  negative[8] = std::byte{0x80};
  EXPECT_EQ(codeOf([&] { decodeAara(negative, "f.aara"); }), ErrorCode::Corrupt);
  auto huge = good;
  for (int i = 5; i < 13; ++i) {
    huge[i] = std::byte{0x7f};
  }
  EXPECT_EQ(codeOf([&] { decodeAara(huge, "f.aara"); }), ErrorCode::Corrupt);
  EXPECT_EQ(codeOf([&] { decodeAara({}, "f.aara"); }), ErrorCode::Corrupt);
  EXPECT_EQ(codeOf([&] { decodeAara(bytesOf({0xff, 'a'}), "f.aara"); }), ErrorCode::Corrupt);
}

TEST(Aara, AFileIsCheckedAgainstItsHeaderBeforeItsDataIsRead) {
  const fs::path file =
      fs::temp_directory_path() / ("vsm-aara-test-" + std::to_string(::getpid()) + ".aara");
  const auto write = [&](const std::vector<std::byte>& bytes, off_t length) {
    std::ofstream(file, std::ios::binary | std::ios::trunc)
        .write(reinterpret_cast<const char*>(bytes.data()),
               static_cast<std::streamsize>(bytes.size()));
    ASSERT_EQ(::truncate(file.c_str(), length), 0);
  };
  const std::vector<std::byte> good = specExample();
  write(good, static_cast<off_t>(good.size()));
  EXPECT_EQ(readAaraFile(file).data, decodeAara(good, "f").data);
  // A sparse file of 64 GiB behind an 85-byte array: refused from its length, not read whole.
  write(good, off_t{64} << 30);
  EXPECT_EQ(messageOf([&] { readAaraFile(file); }),
            file.string() + ": " + std::to_string((std::size_t{64} << 30) - good.size()) +
                " trailing bytes after the .aara data");
  // A header claiming 2^31 x 2^31 vertices in a file of 13 bytes.
  auto huge = good;
  for (int i = 5; i < 13; ++i) {
    huge[i] = static_cast<std::byte>(i == 8 || i == 12 ? 0x7f : 0xff);
  }
  write(huge, 13);
  EXPECT_NE(messageOf([&] { readAaraFile(file); }).find("negative or too large"),
            std::string::npos);
  // A claim that fits size_t but not the file.
  auto large = good;
  large[5] = std::byte{0};
  large[7] = std::byte{0x10};  // 3 x 2 -> 1048576 x 2 vertices
  write(large, 13 + 100);
  EXPECT_EQ(messageOf([&] { readAaraFile(file); }),
            file.string() + ": truncated .aara data: 113 bytes instead of " +
                std::to_string(13 + 1048576 * 2 * 12));
  write({}, 0);
  EXPECT_EQ(codeOf([&] { readAaraFile(file); }), ErrorCode::Corrupt);
  fs::remove(file);
}

/// The header of an 8-bit grey, uncompressed TIFF of `width` x `height` pixels in one strip,
/// followed by a few bytes of pixels only: what a hostile or broken file claims.
std::vector<std::byte> tiffClaiming(std::uint32_t width, std::uint32_t height) {
  std::vector<std::byte> out = bytesOf({'I', 'I', 42, 0, 8, 0, 0, 0});
  const auto u16 = [&](std::uint32_t v) {
    out.push_back(static_cast<std::byte>(v & 0xff));
    out.push_back(static_cast<std::byte>(v >> 8 & 0xff));
  };
  const auto u32 = [&](std::uint32_t v) {
    u16(v & 0xffff);
    u16(v >> 16);
  };
  const std::uint32_t entries[][3] = {
      {256, 4, width}, {257, 4, height}, {258, 3, 8},
      {259, 3, 1},     {262, 3, 1},      {273, 4, 8 + 2 + 9 * 12 + 4},
      {277, 3, 1},     {278, 4, height}, {279, 4, 16}};
  u16(9);
  for (const auto& [tag, type, value] : entries) {
    u16(tag);
    u16(type);
    u32(1);
    type == 3 ? (u16(value), u16(0)) : u32(value);
  }
  u32(0);
  out.resize(out.size() + 16, std::byte{0x80});
  return out;
}

TEST(TextureFile, ImagesAboveThePixelLimitAreRefusedFromTheirHeader) {
  const fs::path dir =
      fs::temp_directory_path() / ("vsm-texture-test-" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const auto write = [&](const std::string& name, const std::vector<std::byte>& bytes) {
    std::ofstream(dir / name, std::ios::binary)
        .write(reinterpret_cast<const char*>(bytes.data()),
               static_cast<std::streamsize>(bytes.size()));
    return dir / name;
  };
  TextureTile tile(64);
  tile.texels()[0] = 200;
  const fs::path small = write("small.tif", encodeTextureTiff(tile));
  EXPECT_EQ(readTextureTile(small, 64 * 64).texels()[0], 200);
  EXPECT_EQ(
      messageOf([&] { readTextureTile(small, 64 * 64 - 1); }),
      "texture '" + small.string() + "' is 64 x 64 pixels, more than limits.texture_pixels (4095)");
  // 20000 x 20000 pixels (400 MB) in a file of 142 bytes: refused by the default limit before
  // anything is allocated.
  const fs::path claim = write("claim.tif", tiffClaiming(20000, 20000));
  EXPECT_EQ(messageOf([&] { readTextureTile(claim); }),
            "texture '" + claim.string() +
                "' is 20000 x 20000 pixels, more than limits.texture_pixels (268435456)");
  // Within the limit the claim is decoded (libtiff pads the short strip): memory stays bounded by
  // the limit, not by the file.
  const fs::path lie = write("lie.tif", tiffClaiming(64, 64));
  EXPECT_EQ(readTextureTile(lie, 64 * 64).size(), 64);
  fs::remove_all(dir);
}

/// `bytes` as the file `file`; returns `file`.
fs::path writeBytes(const fs::path& file, const std::vector<std::byte>& bytes) {
  std::ofstream(file, std::ios::binary)
      .write(reinterpret_cast<const char*>(bytes.data()),
             static_cast<std::streamsize>(bytes.size()));
  return file;
}

/// A 4 x 4 RGBA DDS file, uncompressed, every texel `bgra` (as stored: blue, green, red, alpha).
std::vector<std::byte> ddsFile(std::array<std::uint8_t, 4> bgra) {
  std::vector<std::byte> out = bytesOf({'D', 'D', 'S', ' '});
  const auto u32 = [&](std::uint32_t v) {
    for (int shift = 0; shift < 32; shift += 8) {
      out.push_back(static_cast<std::byte>(v >> shift & 0xff));
    }
  };
  // DDS_HEADER: size, flags (caps, height, width, pitch, pixel format), height, width, pitch,
  // depth, mipmaps, 11 reserved; DDS_PIXELFORMAT: size, flags (RGB + alpha), FourCC, bits,
  // R/G/B/A masks; caps (texture), caps2-4, reserved.
  for (const std::uint32_t v : {124u, 0x100fu, 4u, 4u, 16u, 0u, 0u}) {
    u32(v);
  }
  for (int i = 0; i < 11; ++i) {
    u32(0);
  }
  for (const std::uint32_t v :
       {32u, 0x41u, 0u, 32u, 0xff0000u, 0xff00u, 0xffu, 0xff000000u, 0x1000u, 0u, 0u, 0u, 0u}) {
    u32(v);
  }
  for (int i = 0; i < 16; ++i) {
    for (const std::uint8_t b : bgra) {
      out.push_back(static_cast<std::byte>(b));
    }
  }
  return out;
}

/// A 4 x 4 grey binary PGM: a format OpenImageIO reads that OPC textures never come in.
std::vector<std::byte> pgmFile() {
  std::vector<std::byte> out;
  for (const char c : std::string_view("P5\n4 4\n255\n")) {
    out.push_back(static_cast<std::byte>(c));
  }
  out.resize(out.size() + 16, std::byte{0x80});
  return out;
}

/// A scratch directory with Images/Diffuse/ for the texture file tests, removed afterwards.
class TextureFileTest : public test::TempDirTest {
 protected:
  TextureFileTest() : TempDirTest("texture-file") {}
  void SetUp() override { fs::create_directories(dir_ / "Images" / "Diffuse"); }
  /// The path of `name` in Images/Diffuse/.
  fs::path file(const std::string& name) const { return dir_ / "Images" / "Diffuse" / name; }
  /// `tile` as a PNG file (converted by readPatchTexturePng from our TIFF).
  std::vector<std::byte> pngOf(const TextureTile& tile) const {
    writeBytes(file("source.tif"), encodeTextureTiff(tile));
    PatchInfo info;
    info.setFolder("0_0_0");
    info.setFiles({"Positions.aara", "", "Diffuse\\source.tif"});
    return readPatchTexturePng(dir_, info);
  }
};

/// The texels of `tile`, comparable.
std::vector<std::uint8_t> texelsOf(const TextureTile& tile) {
  return {tile.texels().begin(), tile.texels().end()};
}

/// A 4 x 4 opaque tile with distinct colours (opaque: OpenImageIO's PNG reader premultiplies
/// colour by alpha).
TextureTile sampleTile() {
  TextureTile tile(4);
  for (std::size_t i = 0; i < tile.texels().size(); ++i) {
    tile.texels()[i] = i % 4 == 3 ? 255 : static_cast<std::uint8_t>(i * 3 + 1);
  }
  return tile;
}

TEST_F(TextureFileTest, ATiffReadsUnderItsOwnExtensionInAnyCaseOrUnderAnother) {
  const TextureTile tile = sampleTile();
  for (const char* name : {"tile.tif", "tile.TIFF", "tile.dds", "tile.png"}) {
    const fs::path path = writeBytes(file(name), encodeTextureTiff(tile));
    EXPECT_EQ(texelsOf(readTextureTile(path)), texelsOf(tile)) << name;
  }
}

TEST_F(TextureFileTest, AnOpaqueTileIsStoredAsRgbAGreyOneAsGreyAndOneWithTransparentTexelsAsRgba) {
  const auto channelsOf = [](const fs::path& path) {
    image::Image image;
    std::string error;
    EXPECT_EQ(image::codec().read("tiff", path.string(), 1 << 20, image, error),
              image::Codec::Status::Ok)
        << error;
    return image.fileChannels;
  };
  TextureTile tile = sampleTile();
  TextureTile grey = tile;
  for (std::size_t i = 0; i < grey.texels().size(); i += 4) {
    grey.texels()[i + 1] = grey.texels()[i + 2] = grey.texels()[i];
  }
  const fs::path luminance = writeBytes(file("grey.tif"), encodeTextureTiff(grey));
  EXPECT_EQ(channelsOf(luminance), 1);
  EXPECT_EQ(texelsOf(readTextureTile(luminance)), texelsOf(grey));
  const fs::path rgb = writeBytes(file("opaque.tif"), encodeTextureTiff(tile));
  EXPECT_EQ(channelsOf(rgb), 3);
  EXPECT_EQ(texelsOf(readTextureTile(rgb)), texelsOf(tile));
  tile.at(3, 2)[0] = tile.at(3, 2)[1] = tile.at(3, 2)[2] = tile.at(3, 2)[3] = 0;
  const fs::path rgba = writeBytes(file("holed.tif"), encodeTextureTiff(tile));
  EXPECT_EQ(channelsOf(rgba), 4);
  EXPECT_EQ(texelsOf(readTextureTile(rgba)), texelsOf(tile));
}

TEST_F(TextureFileTest, AWholeTileWithTransparentTexelsReadsBackAsWrittenAndIsLeftAsItWas) {
  // 256 texels a side: 8 strips of 32 rows, each compressed apart; the left quarter is
  // transparent (premultiplied: colour 0), the rest a pattern the predictor cannot flatten.
  TextureTile tile(256);
  for (int y = 0; y < 256; ++y) {
    for (int x = 0; x < 256; ++x) {
      std::uint8_t* t = tile.at(x, y);
      const bool opaque = x >= 64;
      t[0] = opaque ? static_cast<std::uint8_t>(x * 7 + y) : 0;
      t[1] = opaque ? static_cast<std::uint8_t>((x * y) >> 3) : 0;
      t[2] = opaque ? static_cast<std::uint8_t>(255 - y) : 0;
      t[3] = opaque ? 255 : 0;
    }
  }
  const std::vector<std::uint8_t> before = texelsOf(tile);
  const fs::path path = writeBytes(file("whole.tif"), encodeTextureTiff(tile));
  EXPECT_EQ(texelsOf(tile), before);  // the predictor worked on a copy
  EXPECT_EQ(texelsOf(readTextureTile(path)), before);
}

TEST_F(TextureFileTest, AGlbTakesAnOpaqueTileAsJpegAndOneWithTransparentTexelsAsPng) {
  Model model(5);
  PatchInfo info;
  info.setFolder("0_0_0");
  info.setFiles({"Positions.aara", "", "Diffuse\\source.tif"});
  info.stored = GridRect{0, 0, 5, 5};
  // Opaque: JPEG of the colours, which reads back within JPEG's error.
  TextureTile tile(4);
  for (int y = 0; y < 4; ++y) {
    for (int x = 0; x < 4; ++x) {
      std::uint8_t* t = tile.at(x, y);
      t[0] = static_cast<std::uint8_t>(60 + 10 * x), t[1] = 90, t[2] = 120, t[3] = 255;
    }
  }
  writeBytes(file("source.tif"), encodeTextureTiff(tile));
  auto texture = readPatchTexture(dir_, model, info);
  ASSERT_TRUE(texture);
  EXPECT_EQ(texture->mimeType, "image/jpeg");
  const fs::path jpeg = writeBytes(file("back.jpg"), texture->image);
  const TextureTile back = readTextureTile(jpeg);
  ASSERT_EQ(back.size(), 4);
  for (int x = 0; x < 4; ++x) {
    EXPECT_NEAR(back.at(x, 2)[0], 60 + 10 * x, 6) << x;
    EXPECT_NEAR(back.at(x, 2)[2], 120, 6) << x;
  }
  // One transparent texel: PNG, texel for texel.
  tile.at(1, 1)[0] = tile.at(1, 1)[1] = tile.at(1, 1)[2] = tile.at(1, 1)[3] = 0;
  writeBytes(file("source.tif"), encodeTextureTiff(tile));
  texture = readPatchTexture(dir_, model, info);
  ASSERT_TRUE(texture);
  EXPECT_EQ(texture->mimeType, "image/png");
  EXPECT_EQ(texelsOf(readTextureTile(writeBytes(file("back.png"), texture->image))),
            texelsOf(tile));
}

TEST_F(TextureFileTest, APngNamedTifReadsByItsFirstBytes) {
  const TextureTile tile = sampleTile();
  const std::vector<std::byte> png = pngOf(tile);
  for (const char* name : {"tile.png", "tile.tif", "tile.dds"}) {
    const fs::path path = writeBytes(file(name), png);
    EXPECT_EQ(texelsOf(readTextureTile(path)), texelsOf(tile)) << name;
  }
}

TEST_F(TextureFileTest, ADdsReadsUnderItsOwnExtensionOrAsTif) {
  for (const char* name : {"tile.dds", "tile.tif"}) {
    const fs::path path = writeBytes(file(name), ddsFile({10, 20, 30, 40}));
    const TextureTile tile = readTextureTile(path);
    ASSERT_EQ(tile.size(), 4) << name;
    EXPECT_EQ(tile.texels()[0], 30) << name;  // red
    EXPECT_EQ(tile.texels()[1], 20) << name;
    EXPECT_EQ(tile.texels()[2], 10) << name;
    EXPECT_EQ(tile.texels()[3], 40) << name;
  }
}

TEST_F(TextureFileTest, AFileOfAnotherFormatIsRefusedWhateverItsName) {
  // OpenImageIO reads a PGM (under a .tif name once its TIFF reader fails, by trying all its
  // readers); textures come in TIFF, DDS, PNG or JPEG only.
  for (const char* name : {"tile.tif", "tile.pgm", "tile.exr", "tile"}) {
    const fs::path path = writeBytes(file(name), pgmFile());
    EXPECT_EQ(codeOf([&] { readTextureTile(path); }), ErrorCode::Corrupt) << name;
    EXPECT_EQ(messageOf([&] { readTextureTile(path); }),
              "texture '" + path.string() +
                  "' is not a TIFF, DDS, PNG or JPEG image, the formats accepted for textures")
        << name;
  }
}

TEST_F(TextureFileTest, ABrokenFileOfAnAcceptedFormatGivesItsReadersMessage) {
  const std::vector<std::byte> png = pngOf(sampleTile());
  const fs::path path =
      writeBytes(file("tile.tif"), std::vector<std::byte>(png.begin(), png.begin() + 20));
  const std::string message = messageOf([&] { readTextureTile(path); });
  EXPECT_TRUE(message.starts_with("cannot read texture '" + path.string() + "': ")) << message;
  EXPECT_EQ(codeOf([&] { readTextureTile(path); }), ErrorCode::Corrupt);
}

TEST(XmlWriter, WritesWhatPugixmlReadsBackAndLaysOutAsPugixmlSavesIt) {
  detail::XmlWriter writer;
  writer.open("Aardvark");
  writer.open("Patch");
  writer.empty("TagList");
  writer.text("Plain", "0_0_0");
  writer.text("Escaped", "a & b < c > d \"e\" 'f'\x01\x1f\ttab");
  writer.open("Nothing");
  writer.close();
  writer.open("Nested");
  writer.text("nw", "1_0_0");
  writer.close();
  writer.open("LeftOpen");
  writer.text("x", "1");
  const std::string written = std::move(writer).finish();

  pugi::xml_document doc;
  ASSERT_TRUE(doc.load_string(written.c_str(), pugi::parse_default | pugi::parse_declaration));
  const pugi::xml_node patch = doc.child("Aardvark").child("Patch");
  EXPECT_TRUE(patch.child("TagList"));
  EXPECT_STREQ(patch.child_value("Plain"), "0_0_0");
  EXPECT_STREQ(patch.child_value("Escaped"), "a & b < c > d \"e\" 'f'\x01\x1f\ttab");
  EXPECT_TRUE(patch.child("Nothing"));
  EXPECT_STREQ(patch.child("Nested").child_value("nw"), "1_0_0");
  EXPECT_STREQ(patch.child("LeftOpen").child_value("x"), "1");
  EXPECT_NE(written.find("&amp; b &lt; c &gt; d"), std::string::npos);

  // pugixml's own indented save of what it read is the same bytes: other OPC tools, and earlier
  // vsm versions (which wrote through pugixml), see the layout they always saw.
  std::ostringstream saved;
  doc.save(saved, "  ", pugi::format_indent, pugi::encoding_utf8);
  EXPECT_EQ(saved.str(), written);

  // An empty text is an element with an empty text, as pugixml writes a text set to "".
  detail::XmlWriter blank;
  blank.text("Job", "");
  EXPECT_EQ(std::move(blank).finish(), "<?xml version=\"1.0\" encoding=\"utf-8\"?>\n<Job></Job>\n");
}

// The hierarchy's items one to a line, as OPC.md shows them: the same document to a reader, 40%
// fewer bytes in a large hierarchy than pugixml's indented layout.
TEST(XmlWriter, AnElementOpenedOnOneLineHoldsEverythingInItOnThatLine) {
  detail::XmlWriter writer;
  writer.open("Map");
  for (const std::string key : {"1_0_0", "1_0_1"}) {
    writer.open("item", true);
    writer.text("key", key);
    writer.open("val");
    writer.text("nw", key + "&");
    writer.empty("ne");
    writer.close();
    writer.close();
  }
  writer.text("After", "x");
  const std::string written = std::move(writer).finish();
  EXPECT_EQ(written,
            "<?xml version=\"1.0\" encoding=\"utf-8\"?>\n"
            "<Map>\n"
            "  <item><key>1_0_0</key><val><nw>1_0_0&amp;</nw><ne /></val></item>\n"
            "  <item><key>1_0_1</key><val><nw>1_0_1&amp;</nw><ne /></val></item>\n"
            "  <After>x</After>\n"
            "</Map>\n");
  pugi::xml_document doc;
  ASSERT_TRUE(doc.load_string(written.c_str()));
  EXPECT_STREQ(doc.child("Map").last_child().previous_sibling().child("val").child_value("nw"),
               "1_0_1&");
}

TEST(Aara, AMissingFileIsNotFound) {
  EXPECT_EQ(codeOf([] { readAaraFile("/nonexistent/Positions.aara"); }), ErrorCode::NotFound);
}

// ---- the store -------------------------------------------------------------------------------

constexpr int kSize = 9;

/// A surface sampled on a 2 m lattice around an ECEF-like offset; (u, v) in lattice units.
Vec3d surface(int u, int v) {
  return {4.0e6 + 2.0 * u, 5.0e5 + 2.0 * v, 4.9e6 + std::sin(u * 0.3) * 10 + v * 0.5};
}

/// A two-level model: a root over three leaves (the south-east one missing). The north-west
/// leaf's first row is undefined, so that leaf is stored cropped (the root is not: the north-east
/// leaf defines the rest of that row).
Model makeModel() {
  Model model(kSize);
  PatchInfo root;
  root.key = PatchKey::root();
  model.insert(root);
  for (const Quadrant q : {Quadrant::NW, Quadrant::NE, Quadrant::SW}) {
    PatchInfo leaf;
    leaf.key = PatchKey::root().child(q);
    model.insert(leaf);
    const int u0 = static_cast<int>(leaf.key.x) * (kSize - 1);
    const int v0 = static_cast<int>(leaf.key.y) * (kSize - 1);
    Box3d box;
    box.extend(surface(u0, v0));
    box.extend(surface(u0 + kSize - 1, v0 + kSize - 1));
    auto grid = std::make_shared<PatchGrid>(kSize, originFor(box));
    for (int j = 0; j < kSize; ++j) {
      for (int i = 0; i < kSize; ++i) {
        if (v0 + j > 0 || u0 + i > kSize - 1) {
          grid->setGlobal(i, j, surface(u0 + i, v0 + j));
        }
      }
    }
    model.setGrid(leaf.key, grid);
  }
  model.refreshStale([](const PatchInfo&) -> std::shared_ptr<const PatchGrid> { return nullptr; });
  return model;
}

void writeModel(Model& model, const fs::path& dir) {
  OpcWriter writer(dir, OpcWriter::Durability::Deferred);
  // Children before parents, so each parent's box can hold its children's.
  std::vector<PatchKey> keys;
  for (const auto& [key, info] : model.patches()) {
    keys.push_back(key);
  }
  for (auto it = keys.rbegin(); it != keys.rend(); ++it) {
    PatchInfo& info = model.edit(*it);
    writer.writePatch(info, *model.grid(*it), model.childrenBox(*it));
  }
  writer.writeHierarchy(model);
}

std::string readText(const fs::path& file) {
  std::ifstream in(file, std::ios::binary);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

void writeText(const fs::path& file, const std::string& text) {
  std::ofstream(file, std::ios::binary) << text;
}

void replaceIn(const fs::path& file, const std::string& from, const std::string& to) {
  std::string text = readText(file);
  const auto at = text.find(from);
  ASSERT_NE(at, std::string::npos) << from << " not in " << file;
  text.replace(at, from.size(), to);
  writeText(file, text);
}

class OpcStoreTest : public test::TempDirTest {
 protected:
  OpcStoreTest() : TempDirTest("opc") {}
  void SetUp() override {
    model_ = std::make_unique<Model>(makeModel());
    writeModel(*model_, dir_ / "a");
  }

  fs::path opc() const { return dir_ / "a"; }
  fs::path patches() const { return opc() / "Patches"; }

  std::unique_ptr<Model> model_;
};

TEST_F(OpcStoreTest, WriteReadWriteGivesIdenticalFiles) {
  Model read = readOpcModel(opc());
  ASSERT_EQ(read.patchCount(), 4u);
  for (const auto& [key, info] : read.patches()) {
    read.attachGrid(key, std::make_shared<const PatchGrid>(readPatchGrid(opc(), read, info)));
  }
  writeModel(read, dir_ / "b");
  EXPECT_EQ(filesUnder(opc()), filesUnder(dir_ / "b"));
}

TEST_F(OpcStoreTest, ReadBackIsWhatWasWritten) {
  const Model read = readOpcModel(opc());
  EXPECT_EQ(read.gridSize(), kSize);
  for (const auto& [key, info] : model_->patches()) {
    const PatchInfo& other = read.at(key);
    EXPECT_EQ(other.folder(), key.toString());
    EXPECT_EQ(other.childMask, info.childMask);
    EXPECT_EQ(other.globalBox, info.globalBox);
    EXPECT_EQ(other.local2global(), info.local2global());
    EXPECT_EQ(other.stored, info.stored);
    EXPECT_DOUBLE_EQ(other.resolution, info.resolution);
    EXPECT_EQ(readPatchGrid(opc(), read, other), *model_->grid(key)) << key.toString();
  }
}

// A textured model written with deferred durability (an import, an edit's drafts) stores the
// texture coordinates of a whole patch once, in .vsm-shared/ at the OPC's root, and gives every
// patch stored whole a hard link to it; a cropped patch gets its own file. The coordinates read
// back as V2f of the patch's stored vertices. Rewriting a patch replaces its link (the others
// keep their bytes), and a shared file an earlier writer left with other bytes is replaced, not
// used.
TEST_F(OpcStoreTest, TheCoordinatesOfWholePatchesAreOneSharedFile) {
  const fs::path out = dir_ / "textured";
  Model model = makeModel();
  const auto writeAll = [&](OpcWriter& writer) {
    std::vector<PatchKey> keys;
    for (const auto& [key, info] : model.patches()) {
      keys.push_back(key);
    }
    for (auto it = keys.rbegin(); it != keys.rend(); ++it) {
      PatchInfo& info = model.edit(*it);
      writer.writeTexture(info, TextureTile(textureTileSize(kSize)));
      writer.writePatch(info, *model.grid(*it), model.childrenBox(*it));
    }
    writer.writeHierarchy(model);
  };
  {
    OpcWriter writer(out, OpcWriter::Durability::Deferred);
    writeAll(writer);
  }
  const fs::path shared = out / ".vsm-shared" / ("coordinates-" + std::to_string(kSize) + ".aara");
  const PatchInfo& nw = model.at(PatchKey::root().child(Quadrant::NW));  // stored cropped
  const PatchInfo& ne = model.at(PatchKey::root().child(Quadrant::NE));
  ASSERT_NE(nw.stored, ne.stored);
  const Model read = readOpcModel(out);
  for (const auto& [key, info] : read.patches()) {
    const fs::path file = out / "Patches" / info.folder() / "Coordinates.aara";
    ASSERT_EQ(info.coordinatesFile(), "Coordinates.aara");
    const bool whole = info.stored == GridRect{0, 0, kSize, kSize};
    EXPECT_EQ(fs::equivalent(file, shared), whole) << key.toString();
    EXPECT_EQ(fs::hard_link_count(file), whole ? fs::hard_link_count(shared) : 1u);
    const AaraArray coordinates = decodeAara(readPatchCoordinates(out, info), "c");
    ASSERT_EQ(coordinates.sizes, (std::vector<int>{info.stored.width(), info.stored.height()}));
    // The first stored vertex's (u, v): its grid position over the grid's extent.
    float uv[2];
    std::memcpy(uv, coordinates.data.data(), sizeof uv);
    EXPECT_FLOAT_EQ(uv[0], static_cast<float>(info.stored.x0) / (kSize - 1)) << key.toString();
  }
  ASSERT_EQ(ne.stored, (GridRect{0, 0, kSize, kSize}));
  std::uintmax_t whole = 1;  // the shared file's own name
  for (const auto& [key, info] : read.patches()) {
    whole += info.stored == ne.stored ? 1 : 0;
  }
  EXPECT_GE(whole, 3u);  // NE and the root at least
  EXPECT_EQ(fs::hard_link_count(shared), whole);
  EXPECT_TRUE(validateOpc(out).empty());

  // Another writer finds the shared file holding other bytes: it writes a new one and links NE to
  // it; the root keeps the old file, and rewriting NE left it alone.
  const fs::path rootFile =
      out / "Patches" / model.at(PatchKey::root()).folder() / "Coordinates.aara";
  const std::string before = readText(rootFile);
  const fs::path damaged = out / "damaged";
  writeText(damaged, "not coordinates");
  fs::rename(damaged, shared);
  {
    OpcWriter writer(out, OpcWriter::Durability::Deferred);
    PatchInfo& info = model.edit(ne.key);
    writer.writeTexture(info, TextureTile(textureTileSize(kSize)));
    writer.writePatch(info, *model.grid(ne.key), model.childrenBox(ne.key));
  }
  EXPECT_EQ(readText(rootFile), before);
  EXPECT_FALSE(fs::equivalent(rootFile, shared));
  EXPECT_EQ(readText(out / "Patches" / ne.folder() / "Coordinates.aara"), before);
  EXPECT_TRUE(fs::equivalent(out / "Patches" / ne.folder() / "Coordinates.aara", shared));
}

TEST_F(OpcStoreTest, UndefinedBordersAreCroppedAndTheCropRecorded) {
  const PatchInfo& nw = model_->at(PatchKey::root().child(Quadrant::NW));
  EXPECT_EQ(nw.stored, (GridRect{0, 1, kSize, kSize}));
  const AaraArray positions = readAaraFile(patches() / "1_0_0" / "Positions.aara");
  EXPECT_EQ(positions.sizes, (std::vector<std::int32_t>{kSize, kSize - 1}));
  EXPECT_EQ(model_->at(PatchKey::root()).stored, (GridRect{0, 0, kSize, kSize}));
  EXPECT_NE(readText(patches() / "1_0_0" / "Patch.xml").find("<Offset>[0, 1]</Offset>"),
            std::string::npos);
}

/// The full-grid .aara of a decoded grid, as the positions route sends it.
std::vector<std::byte> fullGridAara(const PatchGrid& grid) {
  const std::array<std::int32_t, 2> sizes{grid.size(), grid.size()};
  std::vector<std::byte> out = encodeAaraHeader(AaraType::V3f, sizes);
  const auto floats = std::as_bytes(grid.positions());
  out.insert(out.end(), floats.begin(), floats.end());
  return out;
}

TEST_F(OpcStoreTest, StoredFilesServeTheFullGridAsIsOrWithTheirRowsCopiedIntoPlace) {
  const Model read = readOpcModel(opc());
  // The root is stored whole: its file is the full grid's .aara, byte for byte.
  const PatchInfo& root = read.at(PatchKey::root());
  const auto whole = openFullGridPositions(opc(), kSize, root);
  ASSERT_NE(whole, nullptr);
  EXPECT_EQ(readStoredFile(*whole, "root"), fullGridAara(readPatchGrid(opc(), read, root)));
  // The cropped leaf is not; its rows copied into place give the decoded grid's bytes.
  const PatchInfo& nw = read.at(PatchKey::root().child(Quadrant::NW));
  EXPECT_EQ(openFullGridPositions(opc(), kSize, nw), nullptr);
  const auto full = readFullGridPositions(opc(), kSize, nw);
  ASSERT_TRUE(full.has_value());
  EXPECT_EQ(*full, fullGridAara(readPatchGrid(opc(), read, nw)));
}

TEST_F(OpcStoreTest, WritesTheStandardElementsInOrderAndTheRootLast) {
  const std::string xml = readText(patches() / "0_0_0" / "Patch.xml");
  std::size_t at = 0;
  for (const char* element :
       {"<TagList", "<GeometryType>QuadList", "<Local2Global>[[1, 0, 0, ", "<LocalBoundingBox>",
        "<GlobalBoundingBox>", "<Positions>Positions.aara", "<Textures", "<Vsm>"}) {
    const auto found = xml.find(element, at);
    ASSERT_NE(found, std::string::npos) << element;
    at = found;
  }
  const std::string hierarchy = readText(patches() / "patchhierarchy.xml");
  EXPECT_NE(hierarchy.find("<RootPatch>0_0_0</RootPatch>"), std::string::npos);
  EXPECT_NE(hierarchy.find("<nw>1_0_0</nw>"), std::string::npos);
  EXPECT_EQ(hierarchy.find("<se>"), std::string::npos);
  EXPECT_TRUE(validateOpc(opc()).empty());
}

TEST_F(OpcStoreTest, WritingTheHierarchyRemovesAStaleHierarchyCache) {
  writeText(patches() / "hierarchy.cache", "old");
  EXPECT_FALSE(validateOpc(opc()).empty());
  OpcWriter(opc(), OpcWriter::Durability::EachFile).writeHierarchy(*model_);
  EXPECT_FALSE(fs::exists(patches() / "hierarchy.cache"));
  EXPECT_TRUE(validateOpc(opc()).empty());
}

/// Rewrites a patch's positions as V3d globals with no Local2Global translation, as other tools do.
void toForeignV3d(const fs::path& folder) {
  const fs::path xml = folder / "Patch.xml";
  std::string text = readText(xml);
  const auto l2gStart = text.find("<Local2Global>") + std::strlen("<Local2Global>");
  const auto l2gEnd = text.find("</Local2Global>");
  const auto numbers = text.substr(l2gStart, l2gEnd - l2gStart);
  double m[16];
  std::sscanf(numbers.c_str(), "[[%lf, %lf, %lf, %lf], [%lf, %lf, %lf, %lf], [%lf, %lf, %lf, %lf]",
              &m[0], &m[1], &m[2], &m[3], &m[4], &m[5], &m[6], &m[7], &m[8], &m[9], &m[10], &m[11]);
  const AaraArray f = readAaraFile(folder / "Positions.aara");
  AaraArray d;
  d.type = AaraType::V3d;
  d.sizes = f.sizes;
  for (std::size_t i = 0; i < f.elementCount(); ++i) {
    float v[3];
    std::memcpy(v, f.data.data() + i * 12, 12);
    const double g[3] = {v[0] + m[3], v[1] + m[7], v[2] + m[11]};
    const auto* b = reinterpret_cast<const std::byte*>(g);
    d.data.insert(d.data.end(), b, b + 24);
  }
  fs::remove(folder / "Positions.aara");
  const auto bytes = encodeAara(d);
  std::ofstream(folder / "positions.aara", std::ios::binary)
      .write(reinterpret_cast<const char*>(bytes.data()),
             static_cast<std::streamsize>(bytes.size()));
  text.replace(l2gStart, l2gEnd - l2gStart,
               "[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]");
  // Local is global now.
  const auto globalStart = text.find("<GlobalBoundingBox>") + std::strlen("<GlobalBoundingBox>");
  const std::string global =
      text.substr(globalStart, text.find("</GlobalBoundingBox>") - globalStart);
  const auto localStart = text.find("<LocalBoundingBox>") + std::strlen("<LocalBoundingBox>");
  text.replace(localStart, text.find("</LocalBoundingBox>") - localStart, global);
  const auto posStart = text.find("<Positions>");
  const auto posEnd = text.find("</Positions>") + std::strlen("</Positions>");
  text.replace(posStart, posEnd - posStart, "<Positions>positions.aara</Positions>");
  writeText(xml, text);
}

TEST_F(OpcStoreTest, AForeignLayoutReadsCorrectly) {
  // Another producer: lower-case names, opaque folder names, no extension elements, V3d
  // positions without an origin, optional elements missing.
  const fs::path foreign = dir_ / "foreign";
  fs::create_directories(foreign / "patches");
  const std::map<std::string, std::string> names{
      {"0_0_0", "root"}, {"1_0_0", "a"}, {"1_1_0", "b"}, {"1_0_1", "c"}};
  for (const auto& [ours, theirs] : names) {
    fs::copy(patches() / ours, foreign / "patches" / theirs);
    fs::rename(foreign / "patches" / theirs / "Patch.xml",
               foreign / "patches" / theirs / "patch.xml");
  }
  // The root is uncropped, as other producers write: drop its extension, make it V3d and drop
  // the optional QuadVertexSortOrder. The leaves keep their extension (one is cropped).
  const fs::path root = foreign / "patches" / "root";
  fs::rename(root / "patch.xml", root / "Patch.xml");
  toForeignV3d(root);
  std::string xml = readText(root / "Patch.xml");
  xml.erase(xml.find("<Vsm>"), xml.find("</Vsm>") + 6 - xml.find("<Vsm>"));
  xml.erase(xml.find("<QuadVertexSortOrder>"),
            xml.find("</QuadVertexSortOrder>") + 22 - xml.find("<QuadVertexSortOrder>"));
  writeText(root / "Patch.xml", xml);
  std::string hierarchy = readText(patches() / "patchhierarchy.xml");
  for (const auto& [ours, theirs] : names) {
    for (std::size_t at; (at = hierarchy.find(">" + ours + "<")) != std::string::npos;) {
      hierarchy.replace(at + 1, ours.size(), theirs);
    }
  }
  hierarchy.erase(hierarchy.find("<Vsm>"), hierarchy.find("</Vsm>") + 6 - hierarchy.find("<Vsm>"));
  writeText(foreign / "patches" / "PatchHierarchy.xml", hierarchy);

  const Model read = readOpcModel(foreign);
  ASSERT_EQ(read.patchCount(), 4u);
  EXPECT_EQ(read.gridSize(), kSize);
  EXPECT_EQ(read.at(PatchKey::root()).folder(), "root");
  EXPECT_EQ(read.at({1, 1, 0}).folder(), "b");
  for (const auto& [key, info] : model_->patches()) {
    const PatchGrid grid = readPatchGrid(foreign, read, read.at(key));
    ASSERT_EQ(grid.size(), kSize);
    for (int y = 0; y < kSize; ++y) {
      for (int x = 0; x < kSize; ++x) {
        ASSERT_EQ(grid.defined(x, y), model_->grid(key)->defined(x, y)) << key.toString();
        if (grid.defined(x, y)) {
          const Vec3d a = grid.global(x, y);
          const Vec3d b = model_->grid(key)->global(x, y);
          EXPECT_LT((a - b).norm(), 1e-3) << key.toString() << " " << x << "," << y;
        }
      }
    }
  }
  // The V3d root was re-based: its float32 locals stay small.
  EXPECT_LT(readPatchGrid(foreign, read, read.at(PatchKey::root())).maxAbsLocal(), 1e3);
  for (const Finding& f : validateOpc(foreign)) {
    ADD_FAILURE() << f.where << ": " << f.message;
  }
}

TEST_F(OpcStoreTest, BadHierarchiesAreCorruptAndNamed) {
  const fs::path file = patches() / "patchhierarchy.xml";
  const std::string good = readText(file);
  struct Case {
    std::string from, to, expect;
  };
  const std::vector<Case> cases{
      {"</SubPatchMap>", "", "malformed XML"},
      {"<nw>1_0_0</nw>", "<nw>9_9_9</nw>", "9_9_9"},
      {"<nw>1_0_0</nw>", "<nw>0_0_0</nw>", "reached twice"},
      {"<nw>1_0_0</nw>", "<nw>../1_0_0</nw>", "../1_0_0"},
      {"<nw>1_0_0</nw>", "<nw>a/b</nw>", "a/b"},
      {"<RootPatch>0_0_0</RootPatch>", "<RootPatch>..</RootPatch>", "not a plain folder name"},
  };
  for (const Case& c : cases) {
    writeText(file, good);
    replaceIn(file, c.from, c.to);
    std::string message;
    try {
      readOpcModel(opc());
      ADD_FAILURE() << "accepted " << c.to;
    } catch (const Error& e) {
      EXPECT_EQ(e.code(), ErrorCode::Corrupt) << c.to;
      message = e.what();
    }
    EXPECT_NE(message.find(c.expect), std::string::npos) << message;
    EXPECT_EQ(message.find('\n'), std::string::npos);
    const auto findings = validateOpc(opc());
    ASSERT_EQ(findings.size(), 1u) << c.to;
    EXPECT_NE(findings[0].message.find(c.expect), std::string::npos);
  }
}

// Issue 32, finding 2: a revision records its writer's fencing token (<Vsm><Revision><Fence>),
// which reads back as written; records without one (older models, a single node) still read and
// validate, and a broken token is Corrupt.
TEST_F(OpcStoreTest, AFencingTokenRoundTripsAndItsAbsenceIsValid) {
  const fs::path file = patches() / "patchhierarchy.xml";
  RevisionRecord record;
  record.parent = 1;
  record.time = "2026-12-03T12:00:00Z";
  record.job = "j1";
  record.changed = 2;
  record.nonce = "0a1b2c3d";
  stageHierarchy(opc(), *model_, &record)->commit();
  ASSERT_TRUE(readRevisionRecord(file).has_value());
  EXPECT_FALSE(readRevisionRecord(file)->fence.has_value()) << "no token was given";
  EXPECT_EQ(readText(file).find("<Fence>"), std::string::npos);
  EXPECT_TRUE(validateOpc(opc()).empty());

  record.fence = FencingToken{7'000'000'123, 7587884562315126784};
  stageHierarchy(opc(), *model_, &record)->commit();
  const std::optional<RevisionRecord> read = readRevisionRecord(file);
  ASSERT_TRUE(read && read->fence);
  EXPECT_EQ(*read->fence, *record.fence);
  EXPECT_EQ(read->nonce, record.nonce);
  EXPECT_EQ(readOpcRevision(opc()).record->fence, record.fence);
  const std::string text = readText(file);
  const auto fence = text.find("<Fence>");
  EXPECT_LT(fence, text.find("<Takeover>7000000123</Takeover>")) << text;
  EXPECT_LT(fence, text.find("<Lease>7587884562315126784</Lease>")) << text;
  EXPECT_TRUE(validateOpc(opc()).empty());

  const std::string good = readText(file);
  for (const auto& [from, to] : std::vector<std::pair<std::string, std::string>>{
           {"<Takeover>7000000123</Takeover>", "<Takeover>-1</Takeover>"},
           {"<Takeover>7000000123</Takeover>", ""},
           {"<Lease>7587884562315126784</Lease>", "<Lease>x</Lease>"},
           {"<Lease>7587884562315126784</Lease>", ""}}) {
    writeText(file, good);
    replaceIn(file, from, to);
    EXPECT_EQ(codeOf([&] { readRevisionRecord(file); }), ErrorCode::Corrupt) << to;
    EXPECT_EQ(validateOpc(opc()).size(), 1u) << to;
  }
}

// The hierarchy made through a memo of the last one is the one made anew, publish after publish,
// whatever changed: folders of children whose parents did not change, leaves added and removed,
// and an older version written again.
PatchInfo named(const PatchKey& key, std::string folder) {
  PatchInfo info;
  info.key = key;
  info.setFolder(std::move(folder));
  return info;
}

TEST_F(OpcStoreTest, AHierarchyMadeThroughTheMemoOfTheLastIsTheOneMadeAnew) {
  Model model(kSize);
  model.insert(named(PatchKey::root(), "root"));
  for (int depth = 1; depth <= 6; ++depth) {  // 5,461 patches: many runs
    for (std::uint32_t y = 0; y < (1u << depth); ++y) {
      for (std::uint32_t x = 0; x < (1u << depth); ++x) {
        const PatchKey key{depth, x, y};
        model.insert(named(key, key.toString()));
      }
    }
  }
  const auto staged = [&](const Model& m, HierarchyMemo* memo) {
    return readText(stageHierarchy(opc(), m, nullptr, "patchhierarchy.xml", memo)->staged());
  };
  HierarchyMemo memo;
  std::mt19937 random(7);
  std::vector<Model> versions{model};
  std::size_t reused = 0;
  for (int round = 0; round < 30; ++round) {
    const std::string made = staged(model, &memo);
    EXPECT_EQ(made, staged(model, nullptr)) << "round " << round;
    EXPECT_GT(memo.bytes(), made.size() / 2);
    reused += memo.lastReused().first;
    EXPECT_LT(memo.lastReused().first, memo.lastReused().second);
    versions.push_back(model);
    for (int step = 0; step < 3; ++step) {
      std::vector<PatchKey> keys;
      for (const auto& [key, info] : model.patches()) {
        keys.push_back(key);
      }
      const PatchKey key = keys[random() % keys.size()];
      switch (random() % 3) {
        case 0:  // a new folder, the parent as it was
          model.edit(key).setFolder(key.toString() + "-r" + std::to_string(round));
          break;
        case 1:
          if (key.depth > 0 && model.at(key).isLeaf()) {
            model.eraseLeaf(key);
          }
          break;
        default:
          if (key.depth < 7 && model.find(key.child(Quadrant::SE)) == nullptr) {
            const PatchKey child = key.child(Quadrant::SE);
            model.insert(named(child, child.toString()));
          }
      }
    }
  }
  EXPECT_GT(reused, 29u * 5u) << "a few changes a round leave many runs as they were";
  // A restore: an older version's runs, then the newest again.
  EXPECT_EQ(staged(versions[3], &memo), staged(versions[3], nullptr));
  EXPECT_EQ(staged(model, &memo), staged(model, nullptr));
}

TEST_F(OpcStoreTest, APatchXmlThatIsBrokenIsCorrupt) {
  writeText(patches() / "1_0_0" / "Patch.xml", "<Aardvark><Patch><Local2Global>[[1, 2]");
  EXPECT_EQ(codeOf([&] { readOpcModel(opc()); }), ErrorCode::Corrupt);
  writeText(patches() / "1_0_0" / "Patch.xml",
            "<Aardvark><Patch><Local2Global>[[1, 2]]</Local2Global></Patch></Aardvark>");
  EXPECT_NE(messageOf([&] { readOpcModel(opc()); }).find("16 numbers"), std::string::npos);
}

TEST_F(OpcStoreTest, NoOpcIsNotFound) {
  EXPECT_EQ(codeOf([&] { readOpcModel(dir_ / "missing"); }), ErrorCode::NotFound);
  fs::create_directories(dir_ / "empty");
  EXPECT_EQ(codeOf([&] { readOpcModel(dir_ / "empty"); }), ErrorCode::NotFound);
}

TEST_F(OpcStoreTest, ValidateReportsEachBreak) {
  // 1. A parent vertex moved away from its child's.
  {
    const fs::path file = patches() / "0_0_0" / "Positions.aara";
    AaraArray a = readAaraFile(file);
    float v[3];
    for (std::size_t i = 0;; ++i) {
      std::memcpy(v, a.data.data() + i * 12, 12);
      if (!std::isnan(v[0])) {
        v[2] += 5;
        std::memcpy(a.data.data() + i * 12, v, 12);
        break;
      }
    }
    const auto bytes = encodeAara(a);
    std::ofstream(file, std::ios::binary)
        .write(reinterpret_cast<const char*>(bytes.data()),
               static_cast<std::streamsize>(bytes.size()));
  }
  // 2. A leaf's box off by 1000 km.
  replaceIn(patches() / "1_1_0" / "Patch.xml", "<GlobalBoundingBox>[[4", "<GlobalBoundingBox>[[3");
  // 3. A leaf's positions truncated.
  fs::resize_file(patches() / "1_0_1" / "Positions.aara",
                  fs::file_size(patches() / "1_0_1" / "Positions.aara") - 5);
  const auto findings = validateOpc(opc());
  std::map<std::string, std::vector<std::string>> byPatch;
  for (const Finding& f : findings) {
    byPatch[f.where].push_back(f.message);
  }
  ASSERT_TRUE(byPatch.count("Patches/0_0_0"));
  EXPECT_TRUE(
      std::any_of(byPatch["Patches/0_0_0"].begin(), byPatch["Patches/0_0_0"].end(),
                  [](const std::string& m) { return m.find("reduce") != std::string::npos; }));
  ASSERT_TRUE(byPatch.count("Patches/1_1_0"));
  EXPECT_NE(byPatch["Patches/1_1_0"][0].find("GlobalBoundingBox"), std::string::npos);
  ASSERT_TRUE(byPatch.count("Patches/1_0_1"));
  EXPECT_NE(byPatch["Patches/1_0_1"][0].find("truncated"), std::string::npos);
}

TEST_F(OpcStoreTest, WritingRefusesFolderNamesThatLeaveTheDirectory) {
  OpcWriter writer(opc(), OpcWriter::Durability::EachFile);
  PatchInfo info = model_->at(PatchKey::root());
  info.setFolder("../escape");
  EXPECT_EQ(codeOf([&] { writer.writePatch(info, *model_->grid(PatchKey::root()), {}); }),
            ErrorCode::InvalidArgument);
  EXPECT_FALSE(fs::exists(dir_ / "escape"));
}

}  // namespace
}  // namespace vsm::core
