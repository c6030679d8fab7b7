// importFile: picks the reader by extension and builds the OPC.
#include <algorithm>
#include <cctype>
#include <string>
#include <system_error>

#include "core/common/error.hpp"
#include "core/io/grid_source.hpp"

namespace vsm::core {

Model importFile(const std::filesystem::path& input, const std::filesystem::path& outDir,
                 const ImportOptions& options) {
  // Checked here as well as in buildOpc so that a clash is reported before a large input is opened.
  const std::filesystem::path target = outDir.filename().empty() ? outDir.parent_path() : outDir;
  std::error_code ec;
  if (std::filesystem::exists(std::filesystem::symlink_status(target, ec))) {
    throw Error(ErrorCode::Conflict, "output directory '" + target.string() + "' exists");
  }
  std::string ext = input.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  const auto source =
      (ext == ".pcd" || ext == ".ply") ? openCloudSource(input) : openRasterSource(input);
  return buildOpc(*source, outDir, options);
}

}  // namespace vsm::core
