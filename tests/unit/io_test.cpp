// Tests of core/io: GDAL rasters and PCL clouds as grid sources, and the pyramid builder.
#include <gdal_priv.h>
#include <gtest/gtest.h>
#include <ogr_spatialref.h>
#include <pcl/io/pcd_io.h>
#include <pcl/io/ply_io.h>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iterator>
#include <limits>
#include <map>
#include <optional>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "core/common/error.hpp"
#include "core/durable/writer_lock.hpp"
#include "core/grid/texture_tile.hpp"
#include "core/io/gdal_support.hpp"
#include "core/io/grid_source.hpp"
#include "core/io/texture_source.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/opc_detail.hpp"
#include "core/opc/opc_index.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/texture_file.hpp"
#include "core/opc/validate.hpp"
#include "tests/unit/test_support.hpp"

namespace fs = std::filesystem;
using namespace vsm::core;

namespace {

using test::codeOf;
using test::filesUnder;
using test::messageOf;

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kA = 6378137.0;
constexpr double kF = 1.0 / 298.257223563;

/// WGS 84 geodetic -> ECEF written out independently of the code under test.
Vec3d ecef(double lonDeg, double latDeg, double h) {
  const double lon = lonDeg * M_PI / 180.0;
  const double lat = latDeg * M_PI / 180.0;
  const double e2 = 2 * kF - kF * kF;
  const double n = kA / std::sqrt(1 - e2 * std::sin(lat) * std::sin(lat));
  return {(n + h) * std::cos(lat) * std::cos(lon), (n + h) * std::cos(lat) * std::sin(lon),
          (n * (1 - e2) + h) * std::sin(lat)};
}

double distance(const Vec3d& a, const Vec3d& b) {
  return (a - b).norm();
}

bool undefined(const Vec3d& v) {
  return std::isnan(v.x) && std::isnan(v.y) && std::isnan(v.z);
}

/// A fresh directory under the system temp dir, removed with everything in it.
class TempDir {
 public:
  TempDir() {
    std::string pattern = (fs::temp_directory_path() / "vsm-io-test-XXXXXX").string();
    if (::mkdtemp(pattern.data()) == nullptr) {
      throw std::runtime_error("mkdtemp failed");
    }
    path_ = pattern;
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  const fs::path& path() const { return path_; }
  fs::path operator/(const std::string& name) const { return path_ / name; }
  /// Names of the entries directly inside the directory.
  std::set<std::string> entries() const {
    std::set<std::string> names;
    for (const auto& e : fs::directory_iterator(path_)) {
      names.insert(e.path().filename().string());
    }
    return names;
  }

 private:
  fs::path path_;
};

struct RasterSpec {
  RasterSpec() = default;
  RasterSpec(int w, int h, std::array<double, 6> gt, int code = 4326)
      : width(w), height(h), geoTransform(gt), epsg(code) {}

  int width = 4;
  int height = 3;
  std::array<double, 6> geoTransform{10.0, 0.5, 0, 47.0, 0, -0.25};
  /// EPSG code; 0 for none.
  int epsg = 4326;
  GDALDataType type = GDT_Float32;
  std::optional<double> noData;
  std::optional<double> scale;
  std::optional<double> offset;
};

/// Writes a one-band GeoTIFF with `values` (row-major).
void makeRaster(const fs::path& path, const RasterSpec& spec, const std::vector<double>& values) {
  GDALAllRegister();
  GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("GTiff");
  GDALDatasetUniquePtr ds(
      driver->Create(path.c_str(), spec.width, spec.height, 1, spec.type, nullptr));
  ASSERT_TRUE(ds);
  std::array<double, 6> gt = spec.geoTransform;
  ds->SetGeoTransform(gt.data());
  if (spec.epsg != 0) {
    OGRSpatialReference srs;
    srs.importFromEPSG(spec.epsg);
    ds->SetSpatialRef(&srs);
  }
  GDALRasterBand* band = ds->GetRasterBand(1);
  if (spec.noData) {
    band->SetNoDataValue(*spec.noData);
  }
  if (spec.scale) {
    band->SetScale(*spec.scale);
  }
  if (spec.offset) {
    band->SetOffset(*spec.offset);
  }
  std::vector<double> copy = values;
  ASSERT_EQ(band->RasterIO(GF_Write, 0, 0, spec.width, spec.height, copy.data(), spec.width,
                           spec.height, GDT_Float64, 0, 0, nullptr),
            CE_None);
}

std::vector<Vec3d> readAll(GridSource& source) {
  std::vector<Vec3d> out(static_cast<std::size_t>(source.width()) * source.height());
  source.read(0, 0, source.width(), source.height(), out);
  return out;
}

// ---------------------------------------------------------------------------------------------
// Rasters

TEST(RasterSource, GeographicSamplesBecomeEcefAtTheirPixelCentres) {
  TempDir dir;
  RasterSpec spec;
  std::vector<double> heights;
  for (int i = 0; i < spec.width * spec.height; ++i) {
    heights.push_back(100.0 + 37.5 * i);
  }
  makeRaster(dir / "geo.tif", spec, heights);
  auto source = openRasterSource(dir / "geo.tif");
  ASSERT_EQ(source->width(), 4);
  ASSERT_EQ(source->height(), 3);
  const auto out = readAll(*source);
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 4; ++c) {
      const Vec3d expected =
          ecef(10.0 + (c + 0.5) * 0.5, 47.0 - (r + 0.5) * 0.25, heights[r * 4 + c]);
      EXPECT_LT(distance(out[r * 4 + c], expected), 1e-6) << "sample " << c << "," << r;
    }
  }
}

TEST(RasterSource, KnownPointsOfTheEllipsoidComeOutExactly) {
  // Pixel centres at lon 0, 90, 180 and lat 90, 0, -90, all at height 0.
  TempDir dir;
  RasterSpec spec{3, 3, {-45, 90, 0, 135, 0, -90}};
  makeRaster(dir / "globe.tif", spec, std::vector<double>(9, 0.0));
  const auto out = readAll(*openRasterSource(dir / "globe.tif"));
  const double b = kA * (1 - kF);
  EXPECT_LT(distance(out[3], {kA, 0, 0}), 1e-6);   // lon 0, lat 0
  EXPECT_LT(distance(out[4], {0, kA, 0}), 1e-6);   // lon 90, lat 0
  EXPECT_LT(distance(out[5], {-kA, 0, 0}), 1e-6);  // lon 180, lat 0
  EXPECT_LT(distance(out[1], {0, 0, b}), 1e-6);    // north pole
  EXPECT_LT(distance(out[7], {0, 0, -b}), 1e-6);   // south pole
}

TEST(RasterSource, NoDataAndNanSamplesAreUndefined) {
  TempDir dir;
  RasterSpec spec;
  spec.noData = -9999.0;
  std::vector<double> heights(12, 250.0);
  heights[1] = -9999.0;
  heights[6] = kNaN;
  makeRaster(dir / "holes.tif", spec, heights);
  const auto out = readAll(*openRasterSource(dir / "holes.tif"));
  for (int i = 0; i < 12; ++i) {
    EXPECT_EQ(undefined(out[i]), i == 1 || i == 6) << "sample " << i;
  }
}

TEST(RasterSource, IntegerBandsApplyNoDataScaleAndOffset) {
  TempDir dir;
  RasterSpec spec;
  spec.type = GDT_Int16;
  spec.noData = -32768;
  spec.scale = 0.5;
  spec.offset = 100;
  std::vector<double> raw(12, 40);
  raw[5] = -32768;
  makeRaster(dir / "int16.tif", spec, raw);
  const auto out = readAll(*openRasterSource(dir / "int16.tif"));
  EXPECT_TRUE(undefined(out[5]));
  EXPECT_LT(distance(out[0], ecef(10.25, 46.875, 120.0)), 1e-6);
}

TEST(RasterSource, AWindowReadsTheSameAsTheWholeRaster) {
  TempDir dir;
  RasterSpec spec{9, 7, {-3, 0.01, 0, 12, 0, -0.01}};
  std::vector<double> heights;
  for (int i = 0; i < 63; ++i) {
    heights.push_back(std::sin(i) * 50);
  }
  makeRaster(dir / "w.tif", spec, heights);
  auto source = openRasterSource(dir / "w.tif");
  const auto all = readAll(*source);
  std::vector<Vec3d> window(4 * 3);
  source->read(5, 2, 4, 3, window);
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 4; ++c) {
      EXPECT_EQ(window[r * 4 + c], all[(2 + r) * 9 + 5 + c]);
    }
  }
}

// Windows are served from blocks of 1024^2 samples read whole (raster_source.cpp): windows in
// quadtree order, across block edges, at the raster's edges, larger than a block and back in an
// earlier block all equal the same samples of one read of the whole raster (larger than a block,
// so read directly), and a sample equals the WGS 84 formula.
TEST(RasterSource, WindowsServedFromBlocksEqualTheWholeRaster) {
  TempDir dir;
  const int width = 2600;
  const int height = 1500;
  RasterSpec spec{width, height, {8.0, 1.0 / 3600, 0, 47.0, 0, -1.0 / 3600}};
  spec.noData = -9999;
  std::vector<double> heights;
  for (int row = 0; row < height; ++row) {
    for (int col = 0; col < width; ++col) {
      heights.push_back((row * 131 + col * 17) % 977 == 0 ? -9999.0
                                                          : 300.0 + (row * 7 + col * 3) % 1000);
    }
  }
  makeRaster(dir / "big.tif", spec, heights);
  auto source = openRasterSource(dir / "big.tif");
  const auto all = readAll(*source);
  struct Window {
    int x0, y0, w, h;
  };
  std::vector<Window> windows;
  for (const int y : {0, 256}) {  // a quadtree block of 257-sample windows, then the next
    for (const int x : {0, 256, 512, 768, 1024, 1280}) {
      windows.push_back({x, y, 257, 257});
    }
  }
  windows.push_back({1000, 900, 300, 200});                  // across both block edges
  windows.push_back({width - 257, height - 257, 257, 257});  // the last samples
  windows.push_back({0, 1024, 1100, 20});                    // wider than a block
  windows.push_back({3, 5, 1, 1});                           // back in the first block
  windows.push_back({2047, 1023, 2, 2});                     // four blocks' corner
  for (const Window& win : windows) {
    std::vector<Vec3d> out(static_cast<std::size_t>(win.w) * win.h);
    source->read(win.x0, win.y0, win.w, win.h, out);
    for (int r = 0; r < win.h; ++r) {
      for (int c = 0; c < win.w; ++c) {
        const Vec3d& got = out[static_cast<std::size_t>(r) * win.w + c];
        const Vec3d& want = all[static_cast<std::size_t>(win.y0 + r) * width + win.x0 + c];
        if (std::isnan(want.x)) {
          ASSERT_TRUE(std::isnan(got.x)) << win.x0 << "," << win.y0 << " +" << c << "," << r;
        } else {
          ASSERT_EQ(got, want) << win.x0 << "," << win.y0 << " +" << c << "," << r;
        }
      }
    }
  }
  const int col = 2599, row = 1499;
  std::vector<Vec3d> one(1);
  source->read(col, row, 1, 1, one);
  const double h = heights[static_cast<std::size_t>(row) * width + col];
  EXPECT_LT(distance(one[0], ecef(8.0 + (col + 0.5) / 3600, 47.0 - (row + 0.5) / 3600, h)), 1e-6);
}

// GDAL's block cache is held to its stated bound (GDAL's default, 5 % of RAM, would let an
// import's memory grow with its raster), unless the user set GDAL_CACHEMAX.
TEST(RasterSource, GdalsBlockCacheIsBounded) {
  ASSERT_EQ(std::getenv("GDAL_CACHEMAX"), nullptr) << "the test needs GDAL's default";
  TempDir dir;
  makeRaster(dir / "c.tif", RasterSpec{}, std::vector<double>(12, 1.0));
  openRasterSource(dir / "c.tif");
  EXPECT_EQ(GDALGetCacheMax64(), detail::kGdalBlockCacheBytes);
}

TEST(RasterSource, ARotatedGeotransformIsRejected) {
  TempDir dir;
  RasterSpec spec;
  spec.geoTransform = {10.0, 0.5, 0.01, 47.0, 0, -0.25};
  makeRaster(dir / "rotated.tif", spec, std::vector<double>(12, 1.0));
  EXPECT_EQ(codeOf([&] { openRasterSource(dir / "rotated.tif"); }), ErrorCode::InvalidArgument);
}

TEST(RasterSource, ARasterWithoutCrsIsRejected) {
  TempDir dir;
  RasterSpec spec;
  spec.epsg = 0;
  makeRaster(dir / "nocrs.tif", spec, std::vector<double>(12, 1.0));
  const auto open = [&] { openRasterSource(dir / "nocrs.tif"); };
  EXPECT_EQ(codeOf(open), ErrorCode::InvalidArgument);
  EXPECT_NE(messageOf(open).find("has no coordinate reference system"), std::string::npos);
}

TEST(RasterSource, AMissingFileIsNotFound) {
  EXPECT_EQ(codeOf([] { openRasterSource("/nonexistent/dem.tif"); }), ErrorCode::NotFound);
}

TEST(RasterSource, AFileThatIsNoRasterIsCorruptAndNamedInTheMessage) {
  TempDir dir;
  std::ofstream(dir / "garbage.tif") << "this is not a GeoTIFF\n";
  const auto open = [&] { openRasterSource(dir / "garbage.tif"); };
  EXPECT_EQ(codeOf(open), ErrorCode::Corrupt);
  const std::string message = messageOf(open);
  EXPECT_NE(message.find("garbage.tif"), std::string::npos);
  EXPECT_EQ(message.find('\n'), std::string::npos);
}

/// Pixel centres of `spec` through OGR to WGS 84 lon/lat, then ECEF: the expectation for
/// rasters in other CRSs.
std::vector<Vec3d> ecefThroughOgr(const RasterSpec& spec, const std::vector<double>& heights) {
  OGRSpatialReference from;
  from.importFromEPSG(spec.epsg);
  from.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
  OGRSpatialReference to;
  to.importFromEPSG(4326);
  to.SetAxisMappingStrategy(OAMS_TRADITIONAL_GIS_ORDER);
  std::unique_ptr<OGRCoordinateTransformation> ct(OGRCreateCoordinateTransformation(&from, &to));
  std::vector<Vec3d> out;
  const auto& gt = spec.geoTransform;
  for (int r = 0; r < spec.height; ++r) {
    for (int c = 0; c < spec.width; ++c) {
      double x = gt[0] + (c + 0.5) * gt[1];
      double y = gt[3] + (r + 0.5) * gt[5];
      EXPECT_TRUE(ct->Transform(1, &x, &y));
      out.push_back(ecef(x, y, heights[static_cast<std::size_t>(r * spec.width + c)]));
    }
  }
  return out;
}

TEST(RasterSource, AUtmRasterLandsWithinCentimetresOfOgrsTransform) {
  TempDir dir;
  RasterSpec spec{5, 4, {500000, 30, 0, 5200000, 0, -30}, 32633};
  std::vector<double> heights;
  for (int i = 0; i < 20; ++i) {
    heights.push_back(400 + 3.0 * i);
  }
  makeRaster(dir / "utm.tif", spec, heights);
  const auto out = readAll(*openRasterSource(dir / "utm.tif"));
  const auto expected = ecefThroughOgr(spec, heights);
  for (std::size_t i = 0; i < out.size(); ++i) {
    EXPECT_LT(distance(out[i], expected[i]), 0.02) << "sample " << i;
  }
  // Neighbours on the central meridian are 30 m / 0.9996 (UTM's scale) apart, 3 m higher.
  EXPECT_NEAR(distance(out[0], out[1]), std::hypot(30.0 / 0.9996, 3.0), 0.01);
}

TEST(RasterSource, AGeographicCrsOnAnotherDatumIsShiftedToWgs84) {
  TempDir dir;
  RasterSpec spec{3, 2, {10.0, 0.01, 0, 50.0, 0, -0.01}, 4230};  // ED50
  const std::vector<double> heights(6, 200.0);
  makeRaster(dir / "ed50.tif", spec, heights);
  const auto out = readAll(*openRasterSource(dir / "ed50.tif"));
  const auto expected = ecefThroughOgr(spec, heights);
  for (std::size_t i = 0; i < out.size(); ++i) {
    EXPECT_LT(distance(out[i], expected[i]), 0.02) << "sample " << i;
  }
  // The datum shift is real: taking ED50 lon/lat as WGS 84 would be tens of metres off.
  EXPECT_GT(distance(out[0], ecef(10.005, 49.995, 200.0)), 10.0);
}

TEST(RasterSource, DescribeNamesTheDriverSizeAndCrs) {
  TempDir dir;
  makeRaster(dir / "d.tif", RasterSpec{}, std::vector<double>(12, 1.0));
  EXPECT_EQ(openRasterSource(dir / "d.tif")->describe(), "GTiff 4x3, EPSG:4326 -> ECEF");
}

// ---------------------------------------------------------------------------------------------
// Point clouds

pcl::PointCloud<pcl::PointXYZ> gridCloud(int width, int height) {
  pcl::PointCloud<pcl::PointXYZ> cloud(static_cast<std::uint32_t>(width),
                                       static_cast<std::uint32_t>(height));
  for (int r = 0; r < height; ++r) {
    for (int c = 0; c < width; ++c) {
      cloud.at(c, r) = pcl::PointXYZ(static_cast<float>(c) * 2, static_cast<float>(r) * 3,
                                     static_cast<float>(c * r));
    }
  }
  cloud.at(1, 1).y = std::numeric_limits<float>::quiet_NaN();
  cloud.is_dense = false;
  return cloud;
}

void expectGridOrder(GridSource& source, int width, int height) {
  ASSERT_EQ(source.width(), width);
  ASSERT_EQ(source.height(), height);
  const auto out = readAll(source);
  for (int r = 0; r < height; ++r) {
    for (int c = 0; c < width; ++c) {
      const Vec3d& v = out[static_cast<std::size_t>(r * width + c)];
      if (c == 1 && r == 1) {
        EXPECT_TRUE(undefined(v));
      } else {
        EXPECT_EQ(v, (Vec3d{c * 2.0, r * 3.0, double(c * r)})) << c << "," << r;
      }
    }
  }
}

TEST(CloudSource, AnOrganizedPcdKeepsItsGridOrder) {
  TempDir dir;
  ASSERT_EQ(pcl::io::savePCDFileBinary((dir / "grid.pcd").string(), gridCloud(5, 3)), 0);
  auto source = openCloudSource(dir / "grid.pcd");
  expectGridOrder(*source, 5, 3);
}

TEST(CloudSource, AnUnorganizedPcdIsRejected) {
  TempDir dir;
  pcl::PointCloud<pcl::PointXYZ> cloud;
  for (int i = 0; i < 10; ++i) {
    cloud.push_back(pcl::PointXYZ(i, i, i));
  }
  ASSERT_EQ(pcl::io::savePCDFileASCII((dir / "flat.pcd").string(), cloud), 0);
  const auto open = [&] { openCloudSource(dir / "flat.pcd"); };
  EXPECT_EQ(codeOf(open), ErrorCode::InvalidArgument);
  EXPECT_NE(messageOf(open).find("not organized"), std::string::npos);
}

TEST(CloudSource, AnOrganizedPlyWrittenByPclKeepsItsGridOrder) {
  TempDir dir;
  ASSERT_EQ(pcl::io::savePLYFileBinary((dir / "grid.ply").string(), gridCloud(4, 6)), 0);
  auto source = openCloudSource(dir / "grid.ply");
  expectGridOrder(*source, 4, 6);
}

TEST(CloudSource, APlyGridWithObjInfoColumnsAndRowsKeepsItsGridOrder) {
  TempDir dir;
  std::ofstream(dir / "hand.ply") << "ply\nformat ascii 1.0\nobj_info num_cols 3\n"
                                     "obj_info num_rows 2\nelement vertex 6\nproperty float x\n"
                                     "property float y\nproperty float z\nend_header\n"
                                     "0 0 0\n2 0 0\n4 0 0\n0 3 0\nnan nan nan\n4 3 2\n";
  auto source = openCloudSource(dir / "hand.ply");
  expectGridOrder(*source, 3, 2);
}

TEST(CloudSource, APlyWithoutGridSizeIsRejected) {
  TempDir dir;
  std::ofstream(dir / "list.ply") << "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n"
                                     "property float y\nproperty float z\nend_header\n"
                                     "0 0 0\n1 0 0\n0 1 0\n1 1 0\n";
  EXPECT_EQ(codeOf([&] { openCloudSource(dir / "list.ply"); }), ErrorCode::InvalidArgument);
}

TEST(CloudSource, AMissingCloudIsNotFound) {
  EXPECT_EQ(codeOf([] { openCloudSource("/nonexistent/cloud.pcd"); }), ErrorCode::NotFound);
}

TEST(CloudSource, FilesThatAreNoCloudsAreCorrupt) {
  // PCL itself crashes on some of these (an empty .pcd, a header without fields).
  TempDir dir;
  const std::map<std::string, std::string> files = {
      {"empty.pcd", ""},
      {"text.pcd", "this is not a point cloud\n"},
      {"nofields.pcd", "# .PCD\nVERSION 0.7\nWIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA ascii\n1 2 3\n"},
      {"noz.pcd",
       "FIELDS x y\nSIZE 4 4\nTYPE F F\nWIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA ascii\n1 2\n1 2\n1 "
       "2\n1 2\n"},
      {"short.pcd",
       "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 2\nPOINTS 4\nDATA binary\n123"},
      {"empty.ply", ""},
      {"noz.ply",
       "ply\nformat ascii 1.0\nobj_info num_cols 2\nobj_info num_rows 2\nelement vertex 4\n"
       "property float x\nproperty float y\nend_header\n1 2\n2 3\n3 4\n4 5\n"},
      {"short.ply",
       "ply\nformat ascii 1.0\nobj_info num_cols 3\nobj_info num_rows 2\nelement vertex 4\n"
       "property float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n2 3 3\n3 4 3\n"
       "4 5 3\n"},
  };
  for (const auto& [name, text] : files) {
    std::ofstream(dir / name, std::ios::binary) << text;
    EXPECT_EQ(codeOf([&] { openCloudSource(dir / name); }), ErrorCode::Corrupt) << name;
  }
}

// ---------------------------------------------------------------------------------------------
// The pyramid builder, on synthetic sources

/// A width x height grid whose sample (c, r) is at a position far from the origin (as ECEF
/// coordinates are) that encodes c and r; `defined` says which samples exist. Records the
/// windows read; can fail or cancel after a number of reads.
class SyntheticSource final : public GridSource {
 public:
  SyntheticSource(int width, int height, std::function<bool(int, int)> defined = nullptr)
      : width_(width), height_(height), defined_(std::move(defined)) {}

  static Vec3d position(int c, int r) {
    return {4.0e6 + 10.0 * c + 0.25 * r, -2.0e6 + 10.0 * r, 4.5e6 + std::sin(c * 0.1) * 30.0};
  }

  int width() const override { return width_; }
  int height() const override { return height_; }
  std::string describe() const override { return "synthetic"; }
  void read(int x0, int y0, int w, int h, std::span<Vec3d> out) override {
    windows.push_back({x0, y0, w, h});
    if (failAfter >= 0 && static_cast<int>(windows.size()) > failAfter) {
      throw Error(ErrorCode::Io, "synthetic read failure");
    }
    if (cancelAfter >= 0 && static_cast<int>(windows.size()) >= cancelAfter && cancel) {
      cancel->cancel();
    }
    for (int r = 0; r < h; ++r) {
      for (int c = 0; c < w; ++c) {
        const bool ok = !defined_ || defined_(x0 + c, y0 + r);
        out[static_cast<std::size_t>(r * w + c)] =
            ok ? position(x0 + c, y0 + r) : Vec3d{kNaN, kNaN, kNaN};
      }
    }
  }

  std::vector<std::array<int, 4>> windows;
  int failAfter = -1;
  int cancelAfter = -1;
  CancelToken* cancel = nullptr;

 private:
  int width_;
  int height_;
  std::function<bool(int, int)> defined_;
};

/// float32 rounding of a patch's stored coordinates, with room for the double arithmetic.
double roundingOf(const PatchGrid& grid) {
  return std::ldexp(std::max(grid.maxAbsLocal(), 1.0), -23);
}

std::map<int, std::size_t> patchesPerDepth(const Model& model) {
  std::map<int, std::size_t> counts;
  for (const auto& [key, info] : model.patches()) {
    ++counts[key.depth];
  }
  return counts;
}

ImportOptions withPatchSize(int size) {
  ImportOptions options;
  options.patchSize = size;
  return options;
}

TEST(PyramidBuilder, An300By200RasterWithPatchSize65IsThreeLevelsBelowTheRoot) {
  TempDir dir;
  SyntheticSource source(300, 200);
  const Model model = buildOpc(source, dir / "opc", withPatchSize(65));
  EXPECT_EQ(model.maxDepth(), 3);  // 64 * 2^3 = 512 >= 299 > 64 * 2^2
  // Bottom: columns start at 0, 64, .., 256 (5), rows at 0, 64, 128, 192 (4); above, each level
  // keeps the patches whose area starts inside the raster.
  EXPECT_EQ(patchesPerDepth(model), (std::map<int, std::size_t>{{0, 1}, {1, 2}, {2, 6}, {3, 20}}));
  EXPECT_TRUE(fs::is_directory(dir / "opc" / "Patches"));
}

// Issue 32, finding 8: staging directories of killed imports are swept, and an import whose pid
// repeats (a container's pid 1) is not refused by its earlier life's leftover.
TEST(PyramidBuilder, StagingLeftByAKilledImportIsSweptAndAnImportOfTheSamePidProceeds) {
  TempDir dir;
  const auto leftover = [&](const std::string& name) {
    fs::create_directories(dir / name / "Patches" / "0_0_0");
    std::ofstream(dir / name / "Patches" / "0_0_0" / "Patch.xml") << "half written";
    return dir / name;
  };
  const fs::path samePid = leftover("opc.partial-" + std::to_string(::getpid()));
  const fs::path oldStyle = leftover("opc.partial-1");
  const fs::path other = leftover("other.partial-7-0123abcd");
  const fs::path busy = leftover("opc.partial-9-89abcdef");
  const auto held = durable::WriterLock::acquire(busy);  // an import still writing it
  SyntheticSource source(100, 100);
  EXPECT_NO_THROW(buildOpc(source, dir / "opc", withPatchSize(65)));
  EXPECT_TRUE(fs::is_directory(dir / "opc" / "Patches"));
  EXPECT_FALSE(fs::exists(samePid));
  EXPECT_FALSE(fs::exists(oldStyle));
  EXPECT_TRUE(fs::exists(busy)) << "a staging directory being written was removed";
  EXPECT_TRUE(fs::exists(other)) << "another target's staging is not this import's to sweep";
  EXPECT_EQ(removeAbandonedImports(dir.path()), 1u);  // all targets: `other`, not `busy`
  EXPECT_FALSE(fs::exists(other));
  EXPECT_TRUE(fs::exists(busy));
}

TEST(PyramidBuilder, QuadrantsOutsideTheSourceAreOmitted) {
  TempDir dir;
  SyntheticSource source(300, 200);
  const Model model = buildOpc(source, dir / "opc", withPatchSize(65));
  const PatchInfo& root = model.at(PatchKey::root());
  EXPECT_TRUE(root.hasChild(Quadrant::NW));
  EXPECT_TRUE(root.hasChild(Quadrant::NE));
  EXPECT_FALSE(root.hasChild(Quadrant::SW));  // rows from 256 on: beyond the 200 rows
  EXPECT_FALSE(root.hasChild(Quadrant::SE));
  EXPECT_EQ(model.children({1, 1, 0}).size(), 2u);  // 2_2_0 and 2_2_1; 2_3_x start at column 384
  EXPECT_EQ(model.find({3, 5, 0}), nullptr);        // would start at column 320
  EXPECT_EQ(model.find({3, 0, 4}), nullptr);        // would start at row 256
}

TEST(PyramidBuilder, BottomWindowsOverlapByOneLineAndAreReadOnce) {
  TempDir dir;
  SyntheticSource source(300, 200);
  buildOpc(source, dir / "opc", withPatchSize(65));
  std::multiset<std::array<int, 4>> expected;
  for (int y0 : {0, 64, 128, 192}) {
    for (int x0 : {0, 64, 128, 192, 256}) {
      expected.insert({x0, y0, std::min(65, 300 - x0), std::min(65, 200 - y0)});
    }
  }
  const std::multiset<std::array<int, 4>> read(source.windows.begin(), source.windows.end());
  EXPECT_EQ(read, expected);
}

TEST(PyramidBuilder, EveryLeafVertexIsItsSourceSampleAndPaddingIsUndefined) {
  TempDir dir;
  SyntheticSource source(300, 200);
  const Model model = buildOpc(source, dir / "opc", withPatchSize(65));
  for (const PatchKey& key : model.leaves()) {
    ASSERT_EQ(key.depth, 3);
    const PatchGrid grid = readPatchGrid(dir / "opc", model, model.at(key));
    const double tolerance = roundingOf(grid) + 1e-9;
    for (int j = 0; j < 65; ++j) {
      for (int i = 0; i < 65; ++i) {
        const int c = static_cast<int>(key.x) * 64 + i;
        const int r = static_cast<int>(key.y) * 64 + j;
        if (c < 300 && r < 200) {
          ASSERT_TRUE(grid.defined(i, j)) << key.toString() << " " << i << "," << j;
          ASSERT_LT(distance(grid.global(i, j), SyntheticSource::position(c, r)), tolerance);
        } else {
          ASSERT_FALSE(grid.defined(i, j)) << key.toString() << " " << i << "," << j;
        }
      }
    }
  }
}

/// Checks the pyramid rule on every inner patch: parent (i, j) is union (2i, 2j) of its
/// children, defined exactly where a present child defines that vertex.
void expectParentsAreReducedFromChildren(const fs::path& opc, const Model& model) {
  const int n = model.gridSize();
  const int half = n - 1;
  std::size_t checked = 0;
  for (const auto& [key, info] : model.patches()) {
    if (info.isLeaf()) {
      continue;
    }
    const PatchGrid parent = readPatchGrid(opc, model, info);
    std::array<std::optional<PatchGrid>, 4> children;
    for (const Quadrant q : kQuadrants) {
      if (info.hasChild(q)) {
        children[static_cast<int>(q)].emplace(readPatchGrid(opc, model, model.at(key.child(q))));
      }
    }
    for (int j = 0; j < n; ++j) {
      for (int i = 0; i < n; ++i) {
        std::optional<Vec3d> fromChild;
        double tolerance = roundingOf(parent);
        for (const Quadrant q : kQuadrants) {
          const auto& child = children[static_cast<int>(q)];
          const int cx = 2 * i - (static_cast<int>(q) & 1) * half;
          const int cy = 2 * j - (static_cast<int>(q) >> 1) * half;
          if (child && cx >= 0 && cx <= half && cy >= 0 && cy <= half && child->defined(cx, cy)) {
            fromChild = child->global(cx, cy);
            tolerance += roundingOf(*child);
            break;
          }
        }
        ASSERT_EQ(parent.defined(i, j), fromChild.has_value())
            << key.toString() << " vertex " << i << "," << j;
        if (fromChild) {
          ASSERT_LT(distance(parent.global(i, j), *fromChild), tolerance)
              << key.toString() << " vertex " << i << "," << j;
          ++checked;
        }
      }
    }
  }
  EXPECT_GT(checked, 0u);
}

TEST(PyramidBuilder, EveryParentVertexEqualsTheChildVertexItCameFrom) {
  TempDir dir;
  SyntheticSource source(300, 200);
  const Model model = buildOpc(source, dir / "opc", withPatchSize(65));
  expectParentsAreReducedFromChildren(dir / "opc", model);
}

TEST(PyramidBuilder, UndefinedAreasHaveNoPatchesAndStayUndefinedAbove) {
  TempDir dir;
  // Defined: columns below 150 and a disc in the lower right.
  SyntheticSource source(300, 200, [](int c, int r) {
    return c < 150 || (c - 250) * (c - 250) + (r - 160) * (r - 160) < 400;
  });
  const Model model = buildOpc(source, dir / "opc", withPatchSize(33));
  EXPECT_NE(model.find({4, 4, 0}), nullptr);  // columns 128..160: holds columns 128..149
  EXPECT_EQ(model.find({4, 5, 0}), nullptr);  // columns 160..192: nothing defined
  EXPECT_NE(model.find({4, 7, 4}), nullptr);  // the disc
  expectParentsAreReducedFromChildren(dir / "opc", model);
}

TEST(PyramidBuilder, TheReturnedModelIsTheOneOnDisk) {
  TempDir dir;
  SyntheticSource source(300, 200, [](int c, int r) { return (c / 40 + r / 40) % 3 != 0; });
  const Model built = buildOpc(source, dir / "opc", withPatchSize(33));
  const Model read = readOpcModel(dir / "opc");
  ASSERT_EQ(read.patchCount(), built.patchCount());
  for (const auto& [key, info] : built.patches()) {
    const PatchInfo* other = read.find(key);
    ASSERT_NE(other, nullptr) << key.toString();
    EXPECT_EQ(other->childMask, info.childMask) << key.toString();
    EXPECT_EQ(other->stored, info.stored) << key.toString();
    EXPECT_EQ(other->local2global(), info.local2global()) << key.toString();
    EXPECT_TRUE(other->globalBox.contains(info.globalBox, 1e-3)) << key.toString();
    EXPECT_TRUE(info.globalBox.contains(other->globalBox, 1e-3)) << key.toString();
    EXPECT_EQ(built.grid(key), nullptr);
    EXPECT_FALSE(info.dirty);
    EXPECT_FALSE(info.stale);
  }
}

TEST(PyramidBuilder, HiddenLevelsAreNamedOnlyInTheSecondFileAndReadBackByVsm) {
  TempDir dir;
  SyntheticSource source(300, 200);
  ImportOptions options = withPatchSize(33);
  options.visibleTexelsPerQuad = 4;  // the relief has 1: the two deepest levels are hidden
  const Model built = buildOpc(source, dir / "opc", options);
  ASSERT_EQ(built.maxDepth(), 4);
  const Model read = readOpcModel(dir / "opc");
  ASSERT_EQ(read.patchCount(), built.patchCount());
  std::size_t hidden = 0;
  for (const auto& [key, info] : built.patches()) {
    EXPECT_EQ(info.hidden, key.depth > 2) << key.toString();
    EXPECT_EQ(read.at(key).hidden, info.hidden) << key.toString();
    hidden += info.hidden ? 1 : 0;
    // Tiles: 32 texels a side at the bottom, doubled up to the visible leaves, then 128.
    const int texels = 32 << std::min(4 - key.depth, 2);
    EXPECT_EQ(readPatchTextureTile(dir / "opc", read.at(key)).size(), texels) << key.toString();
  }
  ASSERT_GT(hidden, 0u);
  // What other readers see: the hierarchy alone, which names no hidden patch.
  const detail::OpcContents visible = detail::readOpc(dir / "opc", "patchhierarchy.xml", false);
  EXPECT_EQ(visible.model.patchCount(), built.patchCount() - hidden);
  EXPECT_EQ(visible.model.maxDepth(), 2);
  EXPECT_TRUE(visible.unreachableItems.empty());
  EXPECT_TRUE(validateOpc(dir / "opc").empty());
  // The index keeps the flag.
  const HierarchyStamp stamp = fileStamp(dir / "opc" / "Patches" / "patchhierarchy.xml");
  const std::optional<OpcRevision> decoded =
      decodeOpcIndex(encodeOpcIndex(stamp, read, nullptr), stamp);
  ASSERT_TRUE(decoded);
  for (const auto& [key, info] : read.patches()) {
    EXPECT_EQ(decoded->model.at(key).hidden, info.hidden) << key.toString();
  }
}

/// The whole text of a file.
std::string fileText(const fs::path& file) {
  std::ifstream in(file);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

TEST(PyramidBuilder, TheSecondHierarchyFileMustBeOursAndHoldEveryHiddenItem) {
  TempDir dir;
  SyntheticSource source(300, 200);
  ImportOptions options = withPatchSize(33);
  options.visibleTexelsPerQuad = 4;  // depths 3 and 4 hidden
  ASSERT_EQ(buildOpc(source, dir / "opc", options).maxDepth(), 4);
  const fs::path hierarchy = dir / "opc" / "Patches" / "patchhierarchy.xml";
  const std::string text = fileText(hierarchy);
  const std::size_t at = text.find("<HiddenLevels>");
  ASSERT_NE(at, std::string::npos);
  const std::size_t end = text.find("</HiddenLevels>", at);
  const std::string named = text.substr(at + 14, end - at - 14);
  EXPECT_TRUE(isHiddenHierarchyFileName(named)) << named;
  const auto write = [&](const fs::path& file, const std::string& bytes) {
    std::ofstream(file, std::ios::trunc) << bytes;
  };
  // The name as read from the hierarchy's tail (for removing unnamed files): none for a missing
  // hierarchy, an error (never "none") for one that cannot be read.
  EXPECT_EQ(hiddenHierarchyNamedBy(hierarchy), std::optional<std::string>(named));
  EXPECT_EQ(hiddenHierarchyNamedBy(dir / "opc" / "Patches" / "missing.xml"), std::nullopt);
  EXPECT_EQ(codeOf([&] { hiddenHierarchyNamedBy(dir / "opc" / "Patches" / "0_0_0"); }),
            ErrorCode::Io);
  // <HiddenLevels> names a file of ours beside the hierarchy, which exists.
  for (const std::string& bad : {std::string("../patchhierarchy.xml"), std::string("x.xml"),
                                 std::string("vsm-hidden-0123456789abcdeg.xml"),
                                 std::string("vsm-hidden-0123456789abcdef.xml")}) {
    write(hierarchy, text.substr(0, at + 14) + bad + text.substr(end));
    EXPECT_EQ(codeOf([&] { readOpcModel(dir / "opc"); }), ErrorCode::Corrupt) << bad;
    EXPECT_FALSE(validateOpc(dir / "opc").empty()) << bad;
  }
  // Without it, the model is what other readers see: three levels.
  write(hierarchy, text.substr(0, at) + text.substr(end + 15));
  EXPECT_EQ(readOpcModel(dir / "opc").maxDepth(), 2);
  write(hierarchy, text);
  // A hidden patch's item (depth 3, whose children are at 4) in the file other readers see.
  const fs::path second = dir / "opc" / "Patches" / named;
  const std::string hiddenText = fileText(second);
  const std::size_t item = hiddenText.find("<item><key>3_");
  ASSERT_NE(item, std::string::npos);
  const std::size_t itemEnd = hiddenText.find("</item>", item) + 7;
  const std::string moved = hiddenText.substr(item, itemEnd - item);
  const std::size_t map = text.find("</SubPatchMap>");
  write(hierarchy, text.substr(0, map) + moved + text.substr(map));
  write(second, hiddenText.substr(0, item) + hiddenText.substr(itemEnd));
  EXPECT_EQ(codeOf([&] { readOpcModel(dir / "opc"); }), ErrorCode::Corrupt);
  EXPECT_FALSE(validateOpc(dir / "opc").empty());
  // The same item in both files.
  write(second, hiddenText);
  EXPECT_EQ(codeOf([&] { readOpcModel(dir / "opc"); }), ErrorCode::Corrupt);
  write(hierarchy, text);
  EXPECT_TRUE(validateOpc(dir / "opc").empty());
}

TEST(PyramidBuilder, QuartersBuiltConcurrentlyWriteTheSameFilesAsASerialBuild) {
  TempDir dir;
  auto defined = [](int c, int r) { return (c / 40 + r / 40) % 3 != 0; };
  SyntheticSource serialSource(300, 200, defined);
  const Model serial = buildOpc(serialSource, dir / "serial", withPatchSize(33));
  SyntheticSource parallelSource(300, 200, defined);
  test::ThreadPerTask executor;
  ImportOptions options = withPatchSize(33);
  options.executor = &executor;
  const Model parallel = buildOpc(parallelSource, dir / "parallel", options);
  EXPECT_EQ(executor.batches, 1);
  EXPECT_EQ(parallel.patchCount(), serial.patchCount());
  EXPECT_EQ(parallelSource.windows.size(), serialSource.windows.size());
  const auto a = filesUnder(dir / "serial");
  const auto b = filesUnder(dir / "parallel");
  ASSERT_EQ(a.size(), b.size());
  for (const auto& [path, bytes] : a) {
    ASSERT_TRUE(b.count(path)) << path;
    EXPECT_TRUE(b.at(path) == bytes) << path;
  }
  EXPECT_TRUE(validateOpc(dir / "parallel").empty());
}

TEST(PyramidBuilder, AFailingQuarterFailsAConcurrentImportAndLeavesNothing) {
  TempDir dir;
  SyntheticSource source(300, 200);
  source.failAfter = 7;
  test::ThreadPerTask executor;
  ImportOptions options = withPatchSize(33);
  options.executor = &executor;
  EXPECT_EQ(codeOf([&] { buildOpc(source, dir / "opc", options); }), ErrorCode::Io);
  EXPECT_TRUE(fs::is_empty(dir.path()));
}

TEST(PyramidBuilder, DepthIsTheSmallestWhoseBottomCoversTheSource) {
  // (width, height, patch size) -> depth, bottom patches
  const std::vector<std::tuple<int, int, int, int, std::size_t>> cases = {
      {1, 1, 65, 0, 1},   {65, 65, 65, 0, 1},   {66, 1, 65, 1, 2},  {65, 2, 65, 0, 1},
      {129, 3, 65, 1, 2}, {130, 130, 65, 2, 9}, {3, 200, 3, 7, 100}};
  for (const auto& [w, h, n, depth, bottom] : cases) {
    TempDir dir;
    SyntheticSource source(w, h);
    const Model model = buildOpc(source, dir / "opc", withPatchSize(n));
    EXPECT_EQ(model.maxDepth(), depth) << w << "x" << h << " / " << n;
    EXPECT_EQ(patchesPerDepth(model)[depth], bottom) << w << "x" << h << " / " << n;
    EXPECT_EQ(source.windows.size(), bottom) << w << "x" << h << " / " << n;
  }
}

TEST(PyramidBuilder, AnExistingOutputDirectoryIsAConflictAndNothingIsWritten) {
  TempDir dir;
  fs::create_directory(dir / "opc");
  std::ofstream(dir / "opc" / "keep.txt") << "mine";
  SyntheticSource source(100, 100);
  EXPECT_EQ(codeOf([&] { buildOpc(source, dir / "opc", withPatchSize(33)); }), ErrorCode::Conflict);
  EXPECT_TRUE(source.windows.empty());
  EXPECT_EQ(dir.entries(), std::set<std::string>{"opc"});
  EXPECT_EQ(fs::directory_iterator(dir / "opc")->path().filename(), "keep.txt");
}

TEST(PyramidBuilder, CancellingLeavesNeitherTheOutputNorTheStagingDirectory) {
  TempDir dir;
  CancelToken cancel;
  SyntheticSource source(300, 200);
  source.cancel = &cancel;
  source.cancelAfter = 5;
  ImportOptions options = withPatchSize(33);
  options.cancel = &cancel;
  EXPECT_EQ(codeOf([&] { buildOpc(source, dir / "opc", options); }), ErrorCode::Cancelled);
  EXPECT_EQ(source.windows.size(), 5u);  // stops at the next patch
  EXPECT_TRUE(dir.entries().empty());
}

TEST(PyramidBuilder, ASourceErrorLeavesNeitherTheOutputNorTheStagingDirectory) {
  TempDir dir;
  SyntheticSource source(300, 200);
  source.failAfter = 7;
  EXPECT_EQ(codeOf([&] { buildOpc(source, dir / "opc", withPatchSize(33)); }), ErrorCode::Io);
  EXPECT_TRUE(dir.entries().empty());
}

TEST(PyramidBuilder, ASourceWithoutDefinedSamplesIsRejected) {
  TempDir dir;
  SyntheticSource source(100, 50, [](int, int) { return false; });
  EXPECT_EQ(codeOf([&] { buildOpc(source, dir / "opc", withPatchSize(33)); }),
            ErrorCode::InvalidArgument);
  EXPECT_TRUE(dir.entries().empty());
}

TEST(PyramidBuilder, APatchSizeThatIsNotAPowerOfTwoPlusOneIsRejected) {
  TempDir dir;
  SyntheticSource source(100, 50);
  const auto build = [&] { buildOpc(source, dir / "opc", withPatchSize(100)); };
  EXPECT_EQ(codeOf(build), ErrorCode::InvalidArgument);
  EXPECT_NE(messageOf(build).find("2^n+1"), std::string::npos);
  EXPECT_TRUE(dir.entries().empty());
}

TEST(PyramidBuilder, SamplesTooSparseForTheirOverviewAreLeftOutWithTheirSubtree) {
  // The defined left part plus one sample at an odd column and row far from it: the depth-3
  // overview keeps only even union positions, so that sample's depth-3 patch would be empty and
  // cannot be written; its subtree is left out rather than written as an empty patch.
  TempDir dir;
  auto defined = [](int c, int r) { return c < 100 || (c == 271 && r == 133); };
  SyntheticSource source(300, 200, defined);
  const Model model = buildOpc(source, dir / "opc", withPatchSize(33));
  EXPECT_EQ(model.find({4, 8, 4}), nullptr);
  EXPECT_EQ(model.find({3, 4, 2}), nullptr);
  expectParentsAreReducedFromChildren(dir / "opc", model);
  // The same when the subtrees are built concurrently: the same files, nothing of the dropped
  // subtree left behind.
  SyntheticSource parallelSource(300, 200, defined);
  test::ThreadPerTask executor;
  ImportOptions options = withPatchSize(33);
  options.executor = &executor;
  buildOpc(parallelSource, dir / "parallel", options);
  EXPECT_EQ(filesUnder(dir / "parallel"), filesUnder(dir / "opc"));
}

class RecordingProgress final : public Progress {
 public:
  void report(std::string_view stage, double fraction) override {
    EXPECT_EQ(stage, "import");
    fractions.push_back(fraction);
  }
  std::vector<double> fractions;
};

TEST(PyramidBuilder, ProgressRisesToOneAndNeverFalls) {
  TempDir dir;
  SyntheticSource source(300, 200);
  RecordingProgress progress;
  ImportOptions options = withPatchSize(65);
  options.progress = &progress;
  buildOpc(source, dir / "opc", options);
  ASSERT_FALSE(progress.fractions.empty());
  EXPECT_TRUE(std::is_sorted(progress.fractions.begin(), progress.fractions.end()));
  EXPECT_GT(progress.fractions.front(), 0.0);
  EXPECT_EQ(progress.fractions.back(), 1.0);
}

// ---------------------------------------------------------------------------------------------
// importFile

TEST(ImportFile, AGeoTiffBecomesAnOpcWhoseVerticesAreItsSamples) {
  TempDir dir;
  RasterSpec spec{40, 30, {-84.4, 0.001, 0, 36.4, 0, -0.001}};
  spec.type = GDT_Int16;
  std::vector<double> heights;
  for (int i = 0; i < 40 * 30; ++i) {
    heights.push_back(300 + (i * 7) % 200);
  }
  makeRaster(dir / "dem.tif", spec, heights);
  const Model model = importFile(dir / "dem.tif", dir / "opc", withPatchSize(17));
  EXPECT_EQ(model.maxDepth(), 2);  // 16 * 4 >= 39
  auto source = openRasterSource(dir / "dem.tif");
  const auto samples = readAll(*source);
  for (const PatchKey& key : model.leaves()) {
    const PatchGrid grid = readPatchGrid(dir / "opc", model, model.at(key));
    for (int j = 0; j < 17; ++j) {
      for (int i = 0; i < 17; ++i) {
        const int c = static_cast<int>(key.x) * 16 + i;
        const int r = static_cast<int>(key.y) * 16 + j;
        if (c < 40 && r < 30) {
          ASSERT_LT(distance(grid.global(i, j), samples[static_cast<std::size_t>(r * 40 + c)]),
                    roundingOf(grid));
        }
      }
    }
  }
  expectParentsAreReducedFromChildren(dir / "opc", model);
}

TEST(ImportFile, AnUpperCasePcdExtensionIsReadAsAPointCloud) {
  TempDir dir;
  ASSERT_EQ(pcl::io::savePCDFileBinary((dir / "GRID.PCD").string(), gridCloud(5, 3)), 0);
  const Model model = importFile(dir / "GRID.PCD", dir / "opc", withPatchSize(5));
  ASSERT_EQ(model.maxDepth(), 0);
  const PatchGrid root = readPatchGrid(dir / "opc", model, model.at(PatchKey::root()));
  EXPECT_FALSE(root.defined(1, 1));
  EXPECT_LT(distance(root.global(4, 2), {8, 6, 8}), 1e-5);
  EXPECT_FALSE(root.defined(0, 3));  // padding below the 3 rows
}

TEST(ImportFile, AnExistingOutputDirectoryIsAConflictBeforeTheInputIsOpened) {
  TempDir dir;
  fs::create_directory(dir / "opc");
  EXPECT_EQ(codeOf([&] { importFile("/nonexistent/dem.tif", dir / "opc", ImportOptions{}); }),
            ErrorCode::Conflict);
}

}  // namespace

// ---------------------------------------------------------------------------------------------
// Textures

namespace {

/// Writes an RGB GeoTIFF whose pixel (x, y) is (x * 16, y * 16, 100); georeferenced when `gt` is.
void makeImage(const fs::path& path, int width, int height,
               std::optional<std::array<double, 6>> gt) {
  GDALAllRegister();
  GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("GTiff");
  GDALDatasetUniquePtr ds(driver->Create(path.c_str(), width, height, 3, GDT_Byte, nullptr));
  ASSERT_TRUE(ds);
  if (gt) {
    ds->SetGeoTransform(gt->data());
    OGRSpatialReference srs;
    srs.importFromEPSG(4326);
    ds->SetSpatialRef(&srs);
  }
  std::vector<std::uint8_t> pixels(static_cast<std::size_t>(width) * height * 3);
  for (int y = 0; y < height; ++y) {
    for (int x = 0; x < width; ++x) {
      std::uint8_t* p = pixels.data() + (static_cast<std::size_t>(y) * width + x) * 3;
      p[0] = static_cast<std::uint8_t>(x * 16);
      p[1] = static_cast<std::uint8_t>(y * 16);
      p[2] = 100;
    }
  }
  ASSERT_EQ(ds->RasterIO(GF_Write, 0, 0, width, height, pixels.data(), width, height, GDT_Byte, 3,
                         nullptr, 3, static_cast<GSpacing>(width) * 3, 1, nullptr),
            CE_None);
}

}  // namespace

TEST(TextureSource, AStretchedImageMapsGridEdgesToImageEdges) {
  TempDir dir;
  makeImage(dir / "plain.tif", 16, 8, std::nullopt);
  const TextureSource texture(dir / "plain.tif", 8, 4, std::nullopt);
  EXPECT_FALSE(texture.georeferenced());
  // Grid point -0.5 (the grid's left pixel edge) is the image's left edge; 7.5 its right edge.
  const auto left = texture.imagePoint(-0.5, -0.5);
  ASSERT_TRUE(left);
  EXPECT_DOUBLE_EQ(left->first, 0.0);
  EXPECT_DOUBLE_EQ(left->second, 0.0);
  const auto right = texture.imagePoint(7.5, 3.5);
  ASSERT_TRUE(right);
  EXPECT_DOUBLE_EQ(right->first, 16.0);
  EXPECT_DOUBLE_EQ(right->second, 8.0);
}

TEST(TextureSource, AGeoreferencedImageIsPlacedByGeographicPosition) {
  TempDir dir;
  // The image is twice as fine as the grid and starts one grid sample further west and north.
  makeImage(dir / "geo.tif", 16, 16, std::array<double, 6>{9.5, 0.25, 0, 47.25, 0, -0.125});
  Georeference grid;
  grid.geoTransform = {10.0, 0.5, 0, 47.0, 0, -0.25};
  OGRSpatialReference srs;
  srs.importFromEPSG(4326);
  char* wkt = nullptr;
  srs.exportToWkt(&wkt);
  grid.crsWkt = wkt;
  CPLFree(wkt);
  const TextureSource texture(dir / "geo.tif", 4, 3, grid);
  EXPECT_TRUE(texture.georeferenced());
  // Grid sample (0, 0) has its centre at lon 10.25, lat 46.875: image pixel edge (3, 3).
  const auto p = texture.imagePoint(0, 0);
  ASSERT_TRUE(p);
  EXPECT_NEAR(p->first, 3.0, 1e-9);
  EXPECT_NEAR(p->second, 3.0, 1e-9);

  // Texel (0, 0) of the tile at sample (0, 0) is the quad centre (0.5, 0.5): image (4, 4), the
  // corner of pixels 3 and 4: the bilinear mean of their colours.
  TextureTile tile(2);
  texture.fillTile(0, 0, PatchGrid(3, Mat4d::identity()), tile);
  EXPECT_NEAR(tile.at(0, 0)[0], 3.5 * 16, 1);
  EXPECT_NEAR(tile.at(0, 0)[1], 3.5 * 16, 1);
  EXPECT_EQ(tile.at(0, 0)[2], 100);
  EXPECT_EQ(tile.at(0, 0)[3], 255);
}

TEST(TexturedImport, EveryPatchGetsATileCoordinatesAndXmlAsOpcSays) {
  TempDir dir;
  // 9 x 9 samples with 5 x 5 patches: a root and four leaves.
  std::vector<double> heights(81);
  for (std::size_t i = 0; i < heights.size(); ++i) {
    heights[i] = 100.0 + static_cast<double>(i);
  }
  makeRaster(dir / "dem.tif", RasterSpec(9, 9, {10.0, 0.01, 0, 47.0, 0, -0.01}), heights);
  makeImage(dir / "plain.tif", 16, 16, std::nullopt);
  ImportOptions options;
  options.patchSize = 5;
  options.drape = ImportOptions::Drape::Image;
  options.texture = dir / "plain.tif";
  options.texelsPerQuad = 1;  // the image's 1.8 pixels per sample would choose 2
  const Model model = importFile(dir / "dem.tif", dir / "opc", options);
  EXPECT_EQ(model.patchCount(), 5u);
  for (const auto& [key, info] : model.patches()) {
    EXPECT_EQ(info.textureFile(), "Diffuse\\" + key.toString() + ".tif");
    EXPECT_EQ(info.coordinatesFile(), "Coordinates.aara");
    EXPECT_TRUE(fs::exists(dir / "opc" / "Images" / "Diffuse" / (key.toString() + ".tif")));
    const AaraArray uv =
        readAaraFile(dir / "opc" / "Patches" / key.toString() / "Coordinates.aara");
    EXPECT_EQ(uv.type, AaraType::V2f);
    EXPECT_EQ(uv.sizes, (std::vector<std::int32_t>{info.stored.width(), info.stored.height()}));
  }
  // Read back: the reader sees the same texture entries, and validation passes.
  const Model read = readOpcModel(dir / "opc");
  EXPECT_EQ(read.at(PatchKey::root()).textureFile(), "Diffuse\\0_0_0.tif");
  EXPECT_TRUE(validateOpc(dir / "opc").empty());

  // The root's texel is the mean of the 2 x 2 texels of the child it covers.
  const TextureTile root = readTextureTile(dir / "opc" / "Images" / "Diffuse" / "0_0_0.tif");
  const TextureTile nw = readTextureTile(dir / "opc" / "Images" / "Diffuse" / "1_0_0.tif");
  ASSERT_EQ(root.size(), 4);
  for (int c = 0; c < 4; ++c) {
    const double mean = (nw.at(0, 0)[c] + nw.at(1, 0)[c] + nw.at(0, 1)[c] + nw.at(1, 1)[c]) / 4.0;
    EXPECT_NEAR(root.at(0, 0)[c], mean, 0.5);
  }
  // The leaf's texel (0, 0) covers grid quad centre (0.5, 0.5): image edge coordinate
  // (1 * 16 / 9) -> centre coordinate 1.28, between pixels 1 and 2.
  const double expected = (1.0 * 16.0 / 9.0 - 0.5) * 16.0;
  EXPECT_NEAR(nw.at(0, 0)[0], expected, 1.0);
  EXPECT_NEAR(nw.at(0, 0)[1], expected, 1.0);

  // The served form: image bytes and full-grid coordinates.
  const auto texture = readPatchTexture(dir / "opc", read, read.at(PatchKey::root()));
  ASSERT_TRUE(texture);
  // An opaque tile goes as JPEG.
  ASSERT_GE(texture->image.size(), 8u);
  EXPECT_EQ(texture->mimeType, "image/jpeg");
  EXPECT_EQ(static_cast<unsigned char>(texture->image[0]), 0xFF);
  EXPECT_EQ(static_cast<unsigned char>(texture->image[1]), 0xD8);
  EXPECT_EQ(texture->texcoords.size(), 5u * 5u * 2u);
  EXPECT_FLOAT_EQ(texture->texcoords[(4 * 5 + 4) * 2], 1.0f);
}

TEST(TexturedImport, TilesKeepEveryPixelOfAFinerImage) {
  TempDir dir;
  // 9 x 9 samples with 5 x 5 patches, an image of 36 x 36 pixels stretched over them: 4 pixels
  // per sample, so 4 x 4 texels per grid quad, tiles of 16 texels.
  makeRaster(dir / "dem.tif", RasterSpec(9, 9, {10.0, 0.01, 0, 47.0, 0, -0.01}),
             std::vector<double>(81, 5.0));
  const int side = 36;
  auto pixel = [](int x, int y) {
    return std::array<int, 3>{x * 7, y * 7, (x + y) % 2 * 255};  // a checkerboard in blue
  };
  {
    GDALAllRegister();
    GDALDriver* driver = GetGDALDriverManager()->GetDriverByName("GTiff");
    GDALDatasetUniquePtr ds(
        driver->Create((dir / "fine.tif").c_str(), side, side, 3, GDT_Byte, nullptr));
    ASSERT_TRUE(ds);
    std::vector<std::uint8_t> pixels(static_cast<std::size_t>(side) * side * 3);
    for (int y = 0; y < side; ++y) {
      for (int x = 0; x < side; ++x) {
        for (int c = 0; c < 3; ++c) {
          pixels[(static_cast<std::size_t>(y) * side + x) * 3 + c] =
              static_cast<std::uint8_t>(pixel(x, y)[c]);
        }
      }
    }
    ASSERT_EQ(ds->RasterIO(GF_Write, 0, 0, side, side, pixels.data(), side, side, GDT_Byte, 3,
                           nullptr, 3, side * 3, 1, nullptr),
              CE_None);
  }
  ImportOptions options;
  options.patchSize = 5;
  options.drape = ImportOptions::Drape::Image;
  options.texture = dir / "fine.tif";
  importFile(dir / "dem.tif", dir / "opc", options);
  EXPECT_TRUE(validateOpc(dir / "opc").empty());
  const fs::path images = dir / "opc" / "Images" / "Diffuse";
  const TextureTile root = readTextureTile(images / "0_0_0.tif");
  const TextureTile se = readTextureTile(images / "1_1_1.tif");
  ASSERT_EQ(root.size(), 16);
  ASSERT_EQ(se.size(), 16);
  // Texel (i, j) of the leaf at sample (4, 4) is centred at grid point (4 + (i + 0.5) / 4, ...):
  // grid edge coordinate + 0.5, times 4 pixels per sample: the centre of pixel (18 + i, 18 + j).
  for (int j = 0; j < 16; ++j) {
    for (int i = 0; i < 16; ++i) {
      for (int c = 0; c < 3; ++c) {
        ASSERT_EQ(se.at(i, j)[c], pixel(18 + i, 18 + j)[c]) << i << ", " << j << ", " << c;
      }
      ASSERT_EQ(se.at(i, j)[3], 255);
    }
  }
  // The root's texel (8 + i, 8 + j) is the mean of that leaf's 2 x 2 texels.
  for (int c = 0; c < 4; ++c) {
    const double mean = (se.at(2, 4)[c] + se.at(3, 4)[c] + se.at(2, 5)[c] + se.at(3, 5)[c]) / 4.0;
    EXPECT_NEAR(root.at(9, 10)[c], mean, 0.5);
  }

  // Asked for fewer: 2 texels per quad.
  options.texelsPerQuad = 2;
  importFile(dir / "dem.tif", dir / "opc2", options);
  EXPECT_EQ(readTextureTile(dir / "opc2" / "Images" / "Diffuse" / "1_1_1.tif").size(), 8);
  // The relief at 2 texels per quad: its own tiles upsampled.
  options.drape = ImportOptions::Drape::ShadedRelief;
  options.texture.clear();
  importFile(dir / "dem.tif", dir / "relief2", options);
  const TextureTile relief = readTextureTile(dir / "relief2" / "Images" / "Diffuse" / "1_1_1.tif");
  EXPECT_EQ(relief.size(), 8);
  EXPECT_FALSE(relief.transparent());

  // Not a power of two, too many for the tile size cap, or without a texture: refused, nothing
  // written.
  for (const int bad : {3, -2, 2048, 1 << 30}) {
    options.texelsPerQuad = bad;
    EXPECT_EQ(codeOf([&] { importFile(dir / "dem.tif", dir / "bad", options); }),
              ErrorCode::InvalidArgument)
        << bad;
  }
  options.texelsPerQuad = 2;
  options.drape = ImportOptions::Drape::None;
  EXPECT_EQ(codeOf([&] { importFile(dir / "dem.tif", dir / "bad", options); }),
            ErrorCode::InvalidArgument);
  EXPECT_FALSE(fs::exists(dir / "bad"));
}

TEST(TexturedImport, AMissingTextureFailsAndLeavesNothingBehind) {
  TempDir dir;
  makeRaster(dir / "dem.tif", RasterSpec(9, 9, {10.0, 0.01, 0, 47.0, 0, -0.01}),
             std::vector<double>(81, 5.0));
  ImportOptions options;
  options.patchSize = 5;
  options.drape = ImportOptions::Drape::Image;
  options.texture = dir / "missing.png";
  EXPECT_EQ(codeOf([&] { importFile(dir / "dem.tif", dir / "opc", options); }),
            ErrorCode::NotFound);
  EXPECT_EQ(dir.entries(), (std::set<std::string>{"dem.tif"}));
}
