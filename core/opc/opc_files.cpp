// File-name resolution shared by the OPC reader, the texture reader and validation: letter case,
// safe names, texture entries.
#include <algorithm>
#include <cctype>
#include <string>
#include <system_error>
#include <vector>

#include "core/opc/opc_detail.hpp"

namespace vsm::core::detail {
namespace fs = std::filesystem;

bool equalsIgnoreCase(std::string_view a, std::string_view b) {
  return a.size() == b.size() &&
         std::equal(a.begin(), a.end(), b.begin(), [](unsigned char x, unsigned char y) {
           return std::tolower(x) == std::tolower(y);
         });
}

std::optional<fs::path> findEntry(const fs::path& dir, std::string_view name) {
  std::error_code ec;
  const fs::path exact = dir / std::string(name);
  if (fs::symlink_status(exact, ec).type() != fs::file_type::not_found && !ec) {
    return exact;
  }
  std::optional<fs::path> found;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    if (equalsIgnoreCase(it->path().filename().string(), name)) {
      found = it->path();
      break;
    }
  }
  return found;
}

fs::path entryPath(const fs::path& dir, std::string_view name) {
  std::optional<fs::path> found = findEntry(dir, name);
  return found ? std::move(*found) : dir / std::string(name);
}

bool isSafeName(std::string_view name) {
  return !name.empty() && name != "." && name.find("..") == std::string_view::npos &&
         name.find('/') == std::string_view::npos && name.find('\\') == std::string_view::npos &&
         name.find('\0') == std::string_view::npos;
}

bool isSafeTexturePath(std::string_view path) {
  if (path.empty()) {
    return false;
  }
  std::size_t start = 0;
  while (true) {
    const std::size_t end = path.find_first_of("\\/", start);
    const std::string_view segment =
        path.substr(start, end == std::string_view::npos ? std::string_view::npos : end - start);
    if (!isSafeName(segment)) {
      return false;
    }
    if (end == std::string_view::npos) {
      return true;
    }
    start = end + 1;
  }
}

std::optional<fs::path> findTextureFile(const fs::path& dir, std::string_view entry) {
  if (!isSafeTexturePath(entry)) {
    return std::nullopt;
  }
  std::optional<fs::path> at = findEntry(dir, "Images");
  std::vector<std::string> segments;
  for (std::size_t start = 0;;) {
    const std::size_t end = entry.find_first_of("\\/", start);
    segments.emplace_back(
        entry.substr(start, end == std::string_view::npos ? std::string_view::npos : end - start));
    if (end == std::string_view::npos) {
      break;
    }
    start = end + 1;
  }
  for (std::size_t i = 0; at && i + 1 < segments.size(); ++i) {
    at = findEntry(*at, segments[i]);
  }
  if (!at) {
    return std::nullopt;
  }
  const fs::path name(segments.back());
  if (auto found = findEntry(*at, name.string())) {
    return found;
  }
  // Readers swap the extension (OPC.md): .dds first, then .tif and .tiff.
  for (const char* ext : {".dds", ".tif", ".tiff"}) {
    if (auto found = findEntry(*at, fs::path(name).replace_extension(ext).string())) {
      return found;
    }
  }
  return std::nullopt;
}

}  // namespace vsm::core::detail
