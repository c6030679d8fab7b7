// Organized point clouds through PCL: the cloud's rows and columns are the grid.
#include <pcl/console/print.h>
#include <pcl/io/pcd_io.h>
#include <pcl/io/ply_io.h>
#include <pcl/point_cloud.h>
#include <pcl/point_types.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <exception>
#include <fstream>
#include <limits>
#include <mutex>
#include <sstream>
#include <string>
#include <system_error>
#include <vector>

#include "core/common/error.hpp"
#include "core/io/grid_source.hpp"

namespace vsm::core {
namespace {

// PCL prints its failures itself and only returns -1; we report them as Error. L_ALWAYS rather
// than L_ERROR: PCL's error lines would otherwise reach stderr beside ours, and the CLI promises
// one line per error. This is process-wide, as PCL's console settings are.
void silencePcl() {
  static std::once_flag once;
  std::call_once(once, [] { pcl::console::setVerbosityLevel(pcl::console::L_ALWAYS); });
}

std::string lowerExtension(const std::filesystem::path& path) {
  std::string ext = path.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return ext;
}

[[noreturn]] void corrupt(const std::string& quoted, const std::string& why) {
  throw Error(ErrorCode::Corrupt, "cannot read point cloud " + quoted + ": " + why);
}

/// Checks a PCD header before PCL sees the file: PCL 1.13 dereferences invalid memory on a file
/// whose header lacks FIELDS, SIZE, TYPE, WIDTH, HEIGHT, POINTS or DATA (even an empty file), so
/// only files with a complete, consistent header and x, y, z fields are handed to it.
void checkPcdHeader(const std::filesystem::path& path, const std::string& quoted) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    corrupt(quoted, "cannot open the file");
  }
  std::vector<std::string> fields;
  std::size_t sizes = 0;
  std::size_t types = 0;
  std::size_t counts = 0;
  long long width = -1;
  long long height = -1;
  long long points = -1;
  bool data = false;
  std::string line;
  for (int lineNo = 0; lineNo < 64 && !data && std::getline(in, line); ++lineNo) {
    std::istringstream words(line);
    std::string keyword;
    if (!(words >> keyword) || keyword[0] == '#') {
      continue;
    }
    std::vector<std::string> values;
    for (std::string v; words >> v;) {
      values.push_back(v);
    }
    const auto number = [&](long long& out) {
      if (values.size() != 1) {
        corrupt(quoted, "bad PCD header line '" + line + "'");
      }
      try {
        std::size_t used = 0;
        out = std::stoll(values[0], &used);
        if (used != values[0].size() || out < 0) {
          throw std::invalid_argument("not a count");
        }
      } catch (const std::exception&) {
        corrupt(quoted, "bad PCD header line '" + line + "'");
      }
    };
    if (keyword == "VERSION" || keyword == "VIEWPOINT") {
      continue;
    } else if (keyword == "FIELDS") {
      fields = values;
    } else if (keyword == "SIZE") {
      sizes = values.size();
    } else if (keyword == "TYPE") {
      types = values.size();
    } else if (keyword == "COUNT") {
      counts = values.size();
    } else if (keyword == "WIDTH") {
      number(width);
    } else if (keyword == "HEIGHT") {
      number(height);
    } else if (keyword == "POINTS") {
      number(points);
    } else if (keyword == "DATA") {
      data = values.size() == 1 &&
             (values[0] == "ascii" || values[0] == "binary" || values[0] == "binary_compressed");
      if (!data) {
        corrupt(quoted, "bad PCD header line '" + line + "'");
      }
    } else {
      corrupt(quoted, "not a PCD file (unexpected header line '" + line.substr(0, 40) + "')");
    }
  }
  if (!data || fields.empty() || width < 0 || height < 0 || points < 0) {
    corrupt(quoted, "not a PCD file (incomplete header)");
  }
  if (sizes != fields.size() || types != fields.size() ||
      (counts != 0 && counts != fields.size()) || width * height != points) {
    corrupt(quoted, "inconsistent PCD header");
  }
  for (const char* axis : {"x", "y", "z"}) {
    if (std::find(fields.begin(), fields.end(), axis) == fields.end()) {
      corrupt(quoted, std::string("the PCD file has no field ") + axis);
    }
  }
}

/// Checks that a PLY file has a vertex element with x, y and z properties (PCL would leave
/// missing coordinates unset) and, when it states a grid size, as many vertices as grid cells
/// (PCL would pad or cut silently).
void checkPlyHeader(const std::filesystem::path& path, const std::string& quoted) {
  std::ifstream in(path, std::ios::binary);
  std::string line;
  if (!in || !std::getline(in, line) || line.rfind("ply", 0) != 0) {
    corrupt(quoted, "not a PLY file");
  }
  bool inVertex = false;
  int axes = 0;
  long long vertices = -1;
  long long columns = -1;
  long long rows = -1;
  for (int lineNo = 0; lineNo < 256 && std::getline(in, line); ++lineNo) {
    std::istringstream words(line);
    std::string keyword;
    words >> keyword;
    if (keyword == "end_header") {
      if (axes != 7) {
        corrupt(quoted, "the PLY file has no vertex element with x, y and z");
      }
      if (columns >= 0 && rows >= 0 && columns * rows != vertices) {
        corrupt(quoted, "the PLY grid of " + std::to_string(columns) + " x " +
                            std::to_string(rows) + " does not match its " +
                            std::to_string(vertices) + " vertices");
      }
      return;
    }
    if (keyword == "element") {
      std::string name;
      long long count = -1;
      words >> name >> count;
      inVertex = name == "vertex";
      if (inVertex) {
        vertices = count;
      }
    } else if (keyword == "property" && inVertex) {
      std::string type;
      std::string name;
      words >> type >> name;
      axes |= name == "x" ? 1 : name == "y" ? 2 : name == "z" ? 4 : 0;
    } else if (keyword == "obj_info") {
      std::string name;
      long long value = -1;
      words >> name >> value;
      if (name == "num_cols") {
        columns = value;
      } else if (name == "num_rows") {
        rows = value;
      }
    }
  }
  corrupt(quoted, "not a PLY file (no end_header)");
}

class CloudSource final : public GridSource {
 public:
  explicit CloudSource(const std::filesystem::path& path) {
    silencePcl();
    const std::string quoted = "'" + path.string() + "'";
    std::error_code ec;
    if (!std::filesystem::is_regular_file(path, ec)) {
      throw Error(ErrorCode::NotFound, "point cloud " + quoted + " does not exist");
    }
    const std::string ext = lowerExtension(path);
    const bool ply = ext == ".ply";
    if (ply) {
      checkPlyHeader(path, quoted);
    } else {
      checkPcdHeader(path, quoted);
    }
    int status = -1;
    try {
      status = ply ? pcl::io::loadPLYFile(path.string(), cloud_)
                   : pcl::io::loadPCDFile(path.string(), cloud_);
    } catch (const std::exception& e) {
      corrupt(quoted, e.what());
    }
    if (status < 0) {
      corrupt(quoted, std::string("not a valid ") + (ply ? "PLY" : "PCD") + " file");
    }
    if (static_cast<std::size_t>(cloud_.width) * cloud_.height != cloud_.size()) {
      corrupt(quoted, "the grid size " + std::to_string(cloud_.width) + " x " +
                          std::to_string(cloud_.height) + " does not match the " +
                          std::to_string(cloud_.size()) + " points");
    }
    if (cloud_.height <= 1 || cloud_.width < 1) {
      throw Error(ErrorCode::InvalidArgument,
                  "point cloud " + quoted + " is not organized (" + std::to_string(cloud_.width) +
                      " x " + std::to_string(cloud_.height) +
                      "); only grids of points can be imported" +
                      (ply ? " (a PLY grid needs obj_info num_cols and num_rows)" : ""));
    }
    description_ = std::string(ply ? "PLY" : "PCD") + " organized cloud " +
                   std::to_string(cloud_.width) + "x" + std::to_string(cloud_.height) +
                   ", Cartesian";
  }

  int width() const override { return static_cast<int>(cloud_.width); }
  int height() const override { return static_cast<int>(cloud_.height); }
  std::string describe() const override { return description_; }

  void read(int x0, int y0, int w, int h, std::span<Vec3d> out) override {
    const std::size_t count = static_cast<std::size_t>(w) * static_cast<std::size_t>(h);
    if (x0 < 0 || y0 < 0 || w < 0 || h < 0 || x0 + w > width() || y0 + h > height() ||
        out.size() < count) {
      throw Error(ErrorCode::Internal, "cloud window outside the grid or output too small");
    }
    constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
    for (int r = 0; r < h; ++r) {
      const pcl::PointXYZ* in =
          &cloud_.points[static_cast<std::size_t>(y0 + r) * cloud_.width + x0];
      Vec3d* row = out.data() + static_cast<std::size_t>(r) * w;
      for (int c = 0; c < w; ++c) {
        const pcl::PointXYZ& p = in[c];
        if (std::isfinite(p.x) && std::isfinite(p.y) && std::isfinite(p.z)) {
          row[c] = {p.x, p.y, p.z};
        } else {
          row[c] = {kNaN, kNaN, kNaN};
        }
      }
    }
  }

 private:
  pcl::PointCloud<pcl::PointXYZ> cloud_;
  std::string description_;
};

}  // namespace

std::unique_ptr<GridSource> openCloudSource(const std::filesystem::path& path) {
  return std::make_unique<CloudSource>(path);
}

}  // namespace vsm::core
