#include "core/opc/opc_store.hpp"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <deque>
#include <new>
#include <pugixml.hpp>
#include <set>
#include <sstream>

#include "core/common/error.hpp"
#include "core/common/numbers.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/opc_detail.hpp"
#include "core/opc/texture_file.hpp"

namespace vsm::core {
namespace fs = std::filesystem;

namespace {

[[noreturn]] void corrupt(const fs::path& where, const std::string& message) {
  throw Error(ErrorCode::Corrupt, where.string() + ": " + message);
}

bool equalsIgnoreCase(std::string_view a, std::string_view b) {
  return a.size() == b.size() &&
         std::equal(a.begin(), a.end(), b.begin(), [](unsigned char x, unsigned char y) {
           return std::tolower(x) == std::tolower(y);
         });
}

/// The child element called `name` in any letter case (exact spelling first).
pugi::xml_node childCi(const pugi::xml_node& node, std::string_view name) {
  if (pugi::xml_node exact = node.child(std::string(name).c_str())) {
    return exact;
  }
  for (pugi::xml_node child : node.children()) {
    if (child.type() == pugi::node_element && equalsIgnoreCase(child.name(), name)) {
      return child;
    }
  }
  return {};
}

std::string trimmed(std::string_view text) {
  const auto first = text.find_first_not_of(" \t\r\n");
  if (first == std::string_view::npos) {
    return {};
  }
  const auto last = text.find_last_not_of(" \t\r\n");
  return std::string(text.substr(first, last - first + 1));
}

std::string textOf(const pugi::xml_node& node) {
  return trimmed(node.child_value());
}

pugi::xml_document parseXml(const fs::path& file) {
  const std::vector<std::byte> bytes = detail::readFile(file);
  pugi::xml_document doc;
  const pugi::xml_parse_result result =
      doc.load_buffer(bytes.data(), bytes.size(), pugi::parse_default, pugi::encoding_auto);
  if (!result) {
    corrupt(file, std::string("malformed XML: ") + result.description() + " at byte " +
                      std::to_string(result.offset));
  }
  return doc;
}

std::vector<double> numbersOf(const pugi::xml_node& node, std::size_t expected,
                              const fs::path& file) {
  const std::string text = textOf(node);
  const auto values = parseNumberList(text);
  if (!values || values->size() != expected) {
    corrupt(file, std::string("<") + node.name() + "> must hold " + std::to_string(expected) +
                      " numbers, not '" + text.substr(0, 80) + "'");
  }
  for (const double v : *values) {
    if (!std::isfinite(v)) {
      corrupt(file, std::string("<") + node.name() + "> holds a number that is not finite");
    }
  }
  return *values;
}

Box3d boxOf(const std::vector<double>& v) {
  Box3d box;
  box.min = {std::min(v[0], v[3]), std::min(v[1], v[4]), std::min(v[2], v[5])};
  box.max = {std::max(v[0], v[3]), std::max(v[1], v[4]), std::max(v[2], v[5])};
  return box;
}

std::string formatBox(const Box3d& box) {
  return "[[" + formatDouble(box.min.x) + ", " + formatDouble(box.min.y) + ", " +
         formatDouble(box.min.z) + "], [" + formatDouble(box.max.x) + ", " +
         formatDouble(box.max.y) + ", " + formatDouble(box.max.z) + "]]";
}

std::string formatMatrix(const Mat4d& m) {
  std::string out = "[";
  for (int row = 0; row < 4; ++row) {
    out += row == 0 ? "[" : ", [";
    for (int col = 0; col < 4; ++col) {
      out += (col == 0 ? "" : ", ") + formatDouble(m.m[row * 4 + col]);
    }
    out += "]";
  }
  return out + "]";
}

bool isPowerOfTwoPlusOne(long long n) {
  return n >= 3 && ((n - 1) & (n - 2)) == 0;
}

// ---- durable files ---------------------------------------------------------------------------

void fsyncPath(const fs::path& path, bool directory) {
  const int fd = ::open(path.c_str(), (directory ? O_RDONLY | O_DIRECTORY : O_RDONLY) | O_CLOEXEC);
  if (fd < 0) {
    throwIoError("cannot open for fsync", path.string(), errno);
  }
  if (::fsync(fd) != 0) {
    const int errnum = errno;
    ::close(fd);
    throwIoError("cannot fsync", path.string(), errnum);
  }
  ::close(fd);
}

/// Writes all of `bytes` to `fd`; 0 or the errno of the failure.
int writeAll(int fd, std::span<const std::byte> bytes) {
  std::size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
    if (n < 0) {
      if (errno == EINTR) {
        continue;
      }
      return errno;
    }
    done += static_cast<std::size_t>(n);
  }
  return 0;
}

/// Writes `bytes` to a temporary name beside `target` and renames it into place: a reader sees
/// the old file or the new one, never a part. The file is fsynced before the rename and its
/// directory after it, so after a crash the new file is there complete or not at all.
void writeAtomically(const fs::path& target, std::span<const std::byte> bytes) {
  static std::atomic<unsigned> counter{0};
  const fs::path temp =
      target.parent_path() / ("." + target.filename().string() + ".tmp-" +
                              std::to_string(::getpid()) + "-" + std::to_string(counter++));
  const int fd = ::open(temp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) {
    throwIoError("cannot create", temp.string(), errno);
  }
  auto fail = [&](std::string_view what, int errnum) {
    ::close(fd);
    ::unlink(temp.c_str());
    throwIoError(what, temp.string(), errnum);
  };
  if (const int errnum = writeAll(fd, bytes); errnum != 0) {
    fail("cannot write", errnum);
  }
  if (::fsync(fd) != 0) {
    fail("cannot fsync", errno);
  }
  if (::close(fd) != 0) {
    const int errnum = errno;
    ::unlink(temp.c_str());
    throwIoError("cannot close", temp.string(), errnum);
  }
  if (::rename(temp.c_str(), target.c_str()) != 0) {
    const int errnum = errno;
    ::unlink(temp.c_str());
    throwIoError("cannot rename into", target.string(), errnum);
  }
  fsyncPath(target.parent_path(), true);
}

std::span<const std::byte> bytesOf(const std::string& text) {
  return {reinterpret_cast<const std::byte*>(text.data()), text.size()};
}

std::string xmlText(const pugi::xml_document& doc) {
  std::ostringstream out;
  doc.save(out, "  ", pugi::format_indent, pugi::encoding_utf8);
  return out.str();
}

void addText(pugi::xml_node parent, const char* name, const std::string& text) {
  parent.append_child(name).text().set(text.c_str());
}

// ---- reading ---------------------------------------------------------------------------------

struct ParsedPatch {
  PatchInfo info;
  detail::PatchDetails details;
  std::optional<int> gridSize;  // from the extension
  std::optional<std::pair<int, int>> offset;
};

/// Reads one Patch.xml. Grid-size dependent fields (stored rectangle) are completed by the caller.
ParsedPatch readPatchXml(const fs::path& folderDir, const std::string& folder) {
  ParsedPatch parsed;
  PatchInfo& info = parsed.info;
  detail::PatchDetails& details = parsed.details;
  info.folder = folder;
  const auto xmlFile = detail::findEntry(folderDir, "Patch.xml");
  if (!xmlFile) {
    corrupt(folderDir, "no Patch.xml");
  }
  details.xmlFile = *xmlFile;
  const pugi::xml_document doc = parseXml(*xmlFile);
  const pugi::xml_node patch = childCi(childCi(doc, "Aardvark"), "Patch");
  if (!patch) {
    corrupt(*xmlFile, "no <Aardvark><Patch> element");
  }
  for (const char* name : {"TagList", "GeometryType", "Local2Global", "GlobalBoundingBox",
                           "LocalBoundingBox", "Positions", "Textures"}) {
    if (!childCi(patch, name)) {
      details.missingElements.emplace_back(name);
    }
  }
  details.geometryType = textOf(childCi(patch, "GeometryType"));
  if (const pugi::xml_node m = childCi(patch, "Local2Global")) {
    const std::vector<double> v = numbersOf(m, 16, *xmlFile);
    std::copy(v.begin(), v.end(), info.local2global.m.begin());
    if (!info.local2global.isAffineInvertible()) {
      corrupt(*xmlFile, "<Local2Global> is not an invertible affine transform");
    }
  }
  const pugi::xml_node global = childCi(patch, "GlobalBoundingBox");
  const pugi::xml_node local = childCi(patch, "LocalBoundingBox");
  if (global && local) {
    info.globalBox = boxOf(numbersOf(global, 6, *xmlFile));
    info.localBox = boxOf(numbersOf(local, 6, *xmlFile));
  } else {
    details.boxesFromData = true;
  }
  if (const pugi::xml_node positions = childCi(patch, "Positions")) {
    info.positionsFile = textOf(positions);
  }
  if (!detail::isSafeName(info.positionsFile)) {
    corrupt(*xmlFile, "positions file name '" + info.positionsFile + "' leaves its folder");
  }
  // Textures: the first <Textures> entry and the first coordinates (DiffuseColor1Coordinates when
  // present). Unusable names are ignored (lenient): the patch then reads as untextured.
  if (const pugi::xml_node coordinates = childCi(patch, "Coordinates")) {
    pugi::xml_node entry = childCi(coordinates, "DiffuseColor1Coordinates");
    if (!entry) {
      entry = coordinates.find_child(
          [](const pugi::xml_node& n) { return n.type() == pugi::node_element; });
    }
    const std::string name = entry ? textOf(entry) : std::string();
    if (detail::isSafeName(name)) {
      info.coordinatesFile = name;
    }
  }
  if (const pugi::xml_node textures = childCi(patch, "Textures")) {
    for (pugi::xml_node entry : textures.children()) {
      if (entry.type() == pugi::node_element) {
        const std::string name = textOf(entry);
        if (detail::isSafeTexturePath(name)) {
          info.textureFile = name;
        }
        break;
      }
    }
  }
  if (const pugi::xml_node vsm = childCi(patch, "Vsm")) {
    details.hasExtension = true;
    if (const pugi::xml_node key = childCi(vsm, "Key")) {
      details.extensionKey = textOf(key);
    }
    if (const pugi::xml_node size = childCi(vsm, "GridSize")) {
      const auto n = parseInteger(textOf(size));
      if (!n || !isPowerOfTwoPlusOne(*n) || *n > 32769) {
        corrupt(*xmlFile, "<GridSize> must be 2^n+1, not '" + textOf(size) + "'");
      }
      parsed.gridSize = static_cast<int>(*n);
    }
    if (const pugi::xml_node offset = childCi(vsm, "Offset")) {
      const std::vector<double> v = numbersOf(offset, 2, *xmlFile);
      if (v[0] < 0 || v[1] < 0 || v[0] != std::floor(v[0]) || v[1] != std::floor(v[1]) ||
          v[0] > 32768 || v[1] > 32768) {
        corrupt(*xmlFile, "<Offset> must be two non-negative integers");
      }
      parsed.offset = std::pair{static_cast<int>(v[0]), static_cast<int>(v[1])};
    }
    if (const pugi::xml_node resolution = childCi(vsm, "Resolution")) {
      const auto r = parseDouble(textOf(resolution));
      if (!r || !std::isfinite(*r) || *r < 0) {
        corrupt(*xmlFile, "<Resolution> must be a non-negative number");
      }
      details.extensionResolution = *r;
      info.resolution = *r;
    }
    if (const pugi::xml_node version = childCi(vsm, "Version")) {
      const auto v = parseInteger(textOf(version));
      if (!v || *v < 1) {
        corrupt(*xmlFile, "<Version> must be a positive integer");
      }
      info.version = static_cast<std::uint64_t>(*v);
    }
  }
  return parsed;
}

fs::path positionsPath(const fs::path& patchesDir, const PatchInfo& info) {
  const fs::path folderDir =
      detail::findEntry(patchesDir, info.folder).value_or(patchesDir / info.folder);
  return detail::findEntry(folderDir, info.positionsFile).value_or(folderDir / info.positionsFile);
}

/// Decodes a positions array into a full grid of `gridSize` at `stored`.
PatchGrid gridFromArray(const AaraArray& array, int gridSize, const PatchInfo& info,
                        const fs::path& file) {
  if (array.type != AaraType::V3f && array.type != AaraType::V3d) {
    corrupt(file, "positions must be V3f or V3d, not " + std::string(toString(array.type)));
  }
  if (array.sizes.size() != 2) {
    corrupt(file, "positions must be a 2-D grid, not " + std::to_string(array.sizes.size()) + "-D");
  }
  const GridRect& r = info.stored;
  if (array.sizes[0] != r.width() || array.sizes[1] != r.height()) {
    corrupt(file, "positions are " + std::to_string(array.sizes[0]) + " x " +
                      std::to_string(array.sizes[1]) + ", the patch says " +
                      std::to_string(r.width()) + " x " + std::to_string(r.height()));
  }
  const std::size_t count = static_cast<std::size_t>(r.width()) * r.height();
  if (array.type == AaraType::V3f) {
    PatchGrid grid(gridSize, info.local2global);
    float v[3];
    for (std::size_t i = 0; i < count; ++i) {
      std::memcpy(v, array.data.data() + i * 12, 12);
      const int x = r.x0 + static_cast<int>(i % r.width());
      const int y = r.y0 + static_cast<int>(i / r.width());
      if (v[0] == v[0] && v[1] == v[1] && v[2] == v[2]) {
        grid.setLocal(x, y, {v[0], v[1], v[2]});
      }
    }
    return grid;
  }
  // V3d: re-base on the centre of the values so float32 keeps precision.
  std::vector<Vec3d> values(count);
  Box3d box;
  for (std::size_t i = 0; i < count; ++i) {
    std::memcpy(&values[i], array.data.data() + i * 24, 24);
    if (values[i].x == values[i].x && values[i].y == values[i].y && values[i].z == values[i].z) {
      box.extend(values[i]);
    }
  }
  const Vec3d c = box.empty() ? Vec3d{} : box.center();
  Mat4d l2g = info.local2global;
  for (int row = 0; row < 3; ++row) {
    l2g.m[row * 4 + 3] +=
        l2g.m[row * 4] * c.x + l2g.m[row * 4 + 1] * c.y + l2g.m[row * 4 + 2] * c.z;
  }
  PatchGrid grid(gridSize, l2g);
  for (std::size_t i = 0; i < count; ++i) {
    const Vec3d& p = values[i];
    if (p.x == p.x && p.y == p.y && p.z == p.z) {
      grid.setLocal(r.x0 + static_cast<int>(i % r.width()), r.y0 + static_cast<int>(i / r.width()),
                    {static_cast<float>(p.x - c.x), static_cast<float>(p.y - c.y),
                     static_cast<float>(p.z - c.z)});
    }
  }
  return grid;
}

}  // namespace

// ---- detail ----------------------------------------------------------------------------------

namespace detail {

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

double linearScale(const Mat4d& m) {
  double scale = 0;
  for (int row = 0; row < 3; ++row) {
    scale = std::max(
        scale, std::abs(m.m[row * 4]) + std::abs(m.m[row * 4 + 1]) + std::abs(m.m[row * 4 + 2]));
  }
  return scale;
}

double roundingOf(const PatchGrid& grid) {
  return std::ldexp(grid.maxAbsLocal(), -24) * linearScale(grid.local2global());
}

OpcContents readOpc(const fs::path& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) {
    throw Error(ErrorCode::NotFound, "no OPC at '" + dir.string() + "' (not a directory)");
  }
  const fs::path patchesDir = patchesDirOf(dir);
  const auto hierarchyFile = findEntry(patchesDir, "patchhierarchy.xml");
  if (!hierarchyFile) {
    throw Error(ErrorCode::NotFound,
                "no OPC at '" + dir.string() + "' (no Patches/patchhierarchy.xml)");
  }
  const pugi::xml_document doc = parseXml(*hierarchyFile);
  const pugi::xml_node hierarchy = childCi(childCi(doc, "Aardvark"), "PatchHierarchy");
  if (!hierarchy) {
    corrupt(*hierarchyFile, "no <Aardvark><PatchHierarchy> element");
  }
  std::vector<double> avgSizes;
  if (const pugi::xml_node sizes = childCi(hierarchy, "AvgGeometrySizes")) {
    const auto values = parseNumberList(textOf(sizes));
    if (!values) {
      corrupt(*hierarchyFile, "<AvgGeometrySizes> is not a list of numbers");
    }
    avgSizes = *values;
  }
  const std::string rootFolder = textOf(childCi(hierarchy, "RootPatch"));
  if (rootFolder.empty()) {
    corrupt(*hierarchyFile, "no <RootPatch>");
  }

  // Parent folder -> child folder per quadrant.
  std::map<std::string, std::array<std::string, 4>> subPatches;
  for (pugi::xml_node item : childCi(hierarchy, "SubPatchMap").children()) {
    if (item.type() != pugi::node_element || !equalsIgnoreCase(item.name(), "item")) {
      continue;
    }
    const std::string key = textOf(childCi(item, "key"));
    if (!isSafeName(key)) {
      corrupt(*hierarchyFile, "patch name '" + key + "' is not a plain folder name");
    }
    std::array<std::string, 4> children;
    const pugi::xml_node val = childCi(item, "val");
    for (const Quadrant q : kQuadrants) {
      if (const pugi::xml_node child = childCi(val, toString(q))) {
        const std::string name = textOf(child);
        if (!isSafeName(name)) {
          corrupt(*hierarchyFile, "patch name '" + name + "' is not a plain folder name");
        }
        children[static_cast<int>(q)] = name;
      }
    }
    if (!subPatches.emplace(key, children).second) {
      corrupt(*hierarchyFile, "patch '" + key + "' has two <item> entries");
    }
  }
  if (!isSafeName(rootFolder)) {
    corrupt(*hierarchyFile, "patch name '" + rootFolder + "' is not a plain folder name");
  }

  // Walk from the root; keys come from the position in the tree.
  std::vector<std::pair<PatchKey, ParsedPatch>> parsed;
  std::set<std::string> seen;
  std::deque<std::pair<PatchKey, std::string>> queue{{PatchKey::root(), rootFolder}};
  while (!queue.empty()) {
    auto [key, folder] = queue.front();
    queue.pop_front();
    if (!seen.insert(folder).second) {
      corrupt(*hierarchyFile,
              "patch '" + folder + "' is reached twice (a cycle or a shared child)");
    }
    const auto folderDir = findEntry(patchesDir, folder);
    if (!folderDir || !fs::is_directory(*folderDir, ec)) {
      corrupt(*hierarchyFile,
              "names patch '" + folder + "' but there is no folder Patches/" + folder);
    }
    ParsedPatch patch = readPatchXml(*folderDir, folder);
    patch.info.key = key;
    if (const auto it = subPatches.find(folder); it != subPatches.end()) {
      for (const Quadrant q : kQuadrants) {
        const std::string& child = it->second[static_cast<int>(q)];
        if (!child.empty()) {
          if (key.depth >= PatchKey::kMaxDepth) {
            corrupt(*hierarchyFile, "the hierarchy is deeper than " +
                                        std::to_string(PatchKey::kMaxDepth) + " levels");
          }
          queue.emplace_back(key.child(q), child);
        }
      }
    }
    parsed.emplace_back(key, std::move(patch));
  }

  // The grid size: our extensions when present, else the root's stored positions.
  std::optional<int> gridSize;
  if (const pugi::xml_node size = childCi(childCi(hierarchy, "Vsm"), "GridSize")) {
    const auto n = parseInteger(textOf(size));
    if (!n || !isPowerOfTwoPlusOne(*n) || *n > 32769) {
      corrupt(*hierarchyFile, "<GridSize> must be 2^n+1, not '" + textOf(size) + "'");
    }
    gridSize = static_cast<int>(*n);
  }
  for (auto& [key, patch] : parsed) {
    if (patch.gridSize) {
      if (gridSize && *gridSize != *patch.gridSize) {
        corrupt(patch.details.xmlFile, "grid size " + std::to_string(*patch.gridSize) +
                                           " differs from the model's " +
                                           std::to_string(*gridSize));
      }
      gridSize = patch.gridSize;
    }
  }
  std::map<PatchKey, AaraHeader> headers;
  auto headerOf = [&](const PatchKey& key, const PatchInfo& info) -> const AaraHeader& {
    auto it = headers.find(key);
    if (it == headers.end()) {
      it = headers.emplace(key, readAaraHeader(positionsPath(patchesDir, info))).first;
    }
    return it->second;
  };
  if (!gridSize) {
    const AaraHeader& root = headerOf(parsed.front().first, parsed.front().second.info);
    if (root.sizes.size() != 2 || root.sizes[0] != root.sizes[1] ||
        !isPowerOfTwoPlusOne(root.sizes[0])) {
      corrupt(positionsPath(patchesDir, parsed.front().second.info),
              "the root's positions are not a square grid of 2^n+1 vertices");
    }
    gridSize = root.sizes[0];
  }

  OpcContents contents{Model(*gridSize),
                       patchesDir,
                       *hierarchyFile,
                       avgSizes,
                       static_cast<bool>(childCi(hierarchy, "Vsm")),
                       {},
                       {},
                       {}};
  for (auto& [key, patch] : parsed) {
    PatchInfo& info = patch.info;
    if (patch.offset || !patch.details.hasExtension) {
      // The stored rectangle: offset from our extension, size from the file's header.
      const AaraHeader& header = headerOf(key, info);
      const fs::path file = positionsPath(patchesDir, info);
      if (header.sizes.size() != 2) {
        corrupt(file, "positions must be a 2-D grid");
      }
      const auto [x0, y0] = patch.offset.value_or(std::pair{0, 0});
      info.stored = {x0, y0, x0 + header.sizes[0], y0 + header.sizes[1]};
      if (info.stored.x1 > *gridSize || info.stored.y1 > *gridSize || info.stored.empty()) {
        corrupt(file, "positions of " + std::to_string(header.sizes[0]) + " x " +
                          std::to_string(header.sizes[1]) + " at offset " + std::to_string(x0) +
                          ", " + std::to_string(y0) + " do not fit a " + std::to_string(*gridSize) +
                          " grid");
      }
    } else {
      info.stored = {0, 0, *gridSize, *gridSize};
    }
    if (patch.details.boxesFromData) {
      const PatchGrid grid = readPatchGrid(dir, contents.model, info);
      info.globalBox = grid.globalBox();
      info.localBox = grid.localBox();
    }
    if (!patch.details.extensionResolution) {
      // Foreign OPCs: the viewers' own figure for this depth.
      const std::size_t index = avgSizes.size() - 1 - static_cast<std::size_t>(key.depth);
      info.resolution = static_cast<std::size_t>(key.depth) < avgSizes.size() ? avgSizes[index] : 0;
    }
    contents.patches.emplace(key, std::move(patch.details));
    contents.model.insert(std::move(info));
  }

  for (const auto& [folder, children] : subPatches) {
    if (!seen.count(folder)) {
      contents.unreachableItems.push_back(folder);
    }
  }
  for (fs::directory_iterator it(patchesDir, ec), end; !ec && it != end; it.increment(ec)) {
    if (equalsIgnoreCase(it->path().filename().string(), "hierarchy.cache")) {
      contents.hierarchyCaches.push_back(it->path());
    }
  }
  return contents;
}

}  // namespace detail

// ---- public ----------------------------------------------------------------------------------

fs::path patchesDirOf(const fs::path& dir) {
  const auto found = detail::findEntry(dir, "Patches");
  std::error_code ec;
  if (!found || !fs::is_directory(*found, ec)) {
    throw Error(ErrorCode::NotFound, "no OPC at '" + dir.string() + "' (no Patches directory)");
  }
  return *found;
}

Model readOpcModel(const fs::path& dir) {
  return std::move(detail::readOpc(dir).model);
}

PatchGrid readPatchGrid(const fs::path& dir, const Model& model, const PatchInfo& info) {
  const fs::path file = positionsPath(patchesDirOf(dir), info);
  return gridFromArray(readAaraFile(file), model.gridSize(), info, file);
}

OpcWriter::OpcWriter(fs::path dir, Durability durability)
    : dir_(std::move(dir)), durability_(durability) {
  std::error_code ec;
  fs::create_directories(dir_, ec);
  if (ec) {
    throw Error(ErrorCode::Io, "cannot create '" + dir_.string() + "': " + ec.message());
  }
  if (const auto existing = detail::findEntry(dir_, "Patches")) {
    dir_ = *existing;
  } else {
    dir_ /= "Patches";
    fs::create_directory(dir_, ec);
    if (ec) {
      throw Error(ErrorCode::Io, "cannot create '" + dir_.string() + "': " + ec.message());
    }
    if (durability_ == Durability::EachFile) {
      fsyncPath(dir_.parent_path(), true);
    } else {
      unsynced_ = true;
    }
  }
}

namespace {

/// Direct I/O granularity: file offsets, lengths and buffer addresses in multiples of this (the
/// largest logical block size of common devices).
constexpr std::size_t kDirectBlock = 4096;
/// Files below this size are written through the page cache (XML and small arrays).
constexpr std::size_t kDirectMinimum = 64 * 1024;

/// A per-thread buffer aligned for direct I/O, grown as needed and reused (allocating one per
/// file would fault in and zero fresh pages every time). writePatch builds a positions file in it,
/// so writeDirect sends it without a copy. It keeps the largest file its thread wrote.
std::byte* directBuffer(std::size_t bytes) {
  struct Buffer {
    std::byte* data = nullptr;
    std::size_t capacity = 0;
    ~Buffer() { std::free(data); }
  };
  thread_local Buffer buffer;
  if (buffer.capacity < bytes) {
    std::free(buffer.data);
    buffer.capacity = (bytes + kDirectBlock - 1) / kDirectBlock * kDirectBlock;
    buffer.data = static_cast<std::byte*>(std::aligned_alloc(kDirectBlock, buffer.capacity));
    if (buffer.data == nullptr) {
      buffer.capacity = 0;
      throw std::bad_alloc();
    }
  }
  return buffer.data;
}

/// Gives a patch written without a folder name its standard one, and checks the names.
void nameFolder(PatchInfo& info) {
  if (info.folder.empty()) {
    info.folder = info.key.toString();
  }
  if (!detail::isSafeName(info.folder) || !detail::isSafeName(info.positionsFile)) {
    throw Error(ErrorCode::InvalidArgument,
                "patch folder '" + info.folder + "' is not a plain name");
  }
}

}  // namespace

std::string textureEntryFor(std::string_view folder) {
  return std::string(kTextureLayer) + "\\" + std::string(folder) + ".tif";
}

void OpcWriter::writeTexture(PatchInfo& info, const TextureTile& tile) {
  nameFolder(info);
  writeFile(imagesLayerDir() / (info.folder + ".tif"), encodeTextureTiff(tile));
  info.textureFile = textureEntryFor(info.folder);
}

void OpcWriter::writePatch(PatchInfo& info, const PatchGrid& grid, Box3d childrenBox) {
  // By value: callers may pass info.globalBox, which is overwritten below.
  if (!grid.anyDefined()) {
    throw Error(ErrorCode::InvalidArgument,
                "patch " + info.key.toString() + " has no defined vertex to write");
  }
  nameFolder(info);
  if (!info.textureFile.empty() && info.textureFile != textureEntryFor(info.folder)) {
    throw Error(ErrorCode::InvalidArgument, "patch " + info.folder + " names texture '" +
                                                info.textureFile +
                                                "', which this writer does not write");
  }
  const bool durable = durability_ == Durability::EachFile;
  const fs::path folderDir = dir_ / info.folder;
  std::error_code ec;
  if (fs::create_directory(folderDir, ec)) {
    if (durable) {
      fsyncPath(dir_, true);
    } else {
      unsynced_ = true;
    }
  } else if (ec) {
    throw Error(ErrorCode::Io, "cannot create '" + folderDir.string() + "': " + ec.message());
  }

  const PatchGrid::Summary summary = grid.summarize();
  info.local2global = grid.local2global();
  info.localBox = summary.localBox;
  info.globalBox = grid.local2global().isTranslation()
                       ? transformBox(info.local2global, info.localBox)
                       : grid.globalBox();
  info.globalBox.extend(childrenBox);
  info.localBox.extend(transformBox(grid.local2global().inverse(), childrenBox));
  info.resolution = summary.resolution;
  info.stored = summary.definedRect;
  const GridRect& r = info.stored;

  // The file's bytes built in place, in this thread's buffer for direct writes: the header, then
  // the stored rows.
  const std::int32_t sizes[2] = {r.width(), r.height()};
  const std::vector<std::byte> header = encodeAaraHeader(AaraType::V3f, sizes);
  const std::size_t rowBytes = static_cast<std::size_t>(r.width()) * 12;
  const std::span<std::byte> positions(
      directBuffer(header.size() + rowBytes * static_cast<std::size_t>(r.height())),
      header.size() + rowBytes * static_cast<std::size_t>(r.height()));
  std::memcpy(positions.data(), header.data(), header.size());
  const std::span<const float> all = grid.positions();
  std::byte* out = positions.data() + header.size();
  for (int y = r.y0; y < r.y1; ++y) {
    const std::size_t first = (static_cast<std::size_t>(y) * grid.size() + r.x0) * 3;
    std::memcpy(out, all.data() + first, rowBytes);
    out += rowBytes;
  }
  // Undefined vertices are written as three NaNs whatever NaN payload they hold.
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (std::size_t i = header.size(); i < positions.size(); i += 12) {
    float v[3];
    std::memcpy(v, positions.data() + i, 12);
    if (!(v[0] == v[0] && v[1] == v[1] && v[2] == v[2])) {
      v[0] = v[1] = v[2] = nan;
      std::memcpy(positions.data() + i, v, 12);
    }
  }
  const fs::path positionsFile = folderDir / info.positionsFile;
  writeFile(positionsFile, positions);

  info.coordinatesFile.clear();
  if (!info.textureFile.empty()) {
    // Texture coordinates of the stored vertices, before the Patch.xml naming them.
    AaraArray coordinates;
    coordinates.type = AaraType::V2f;
    coordinates.sizes = {r.width(), r.height()};
    const std::vector<float> uvs =
        textureCoordinates(grid.size(), r.x0, r.y0, r.width(), r.height());
    coordinates.data.resize(uvs.size() * sizeof(float));
    std::memcpy(coordinates.data.data(), uvs.data(), coordinates.data.size());
    info.coordinatesFile = "Coordinates.aara";
    writeFile(folderDir / info.coordinatesFile, encodeAara(coordinates));
  }

  pugi::xml_document doc;
  pugi::xml_node decl = doc.append_child(pugi::node_declaration);
  decl.append_attribute("version") = "1.0";
  decl.append_attribute("encoding") = "utf-8";
  pugi::xml_node patch = doc.append_child("Aardvark").append_child("Patch");
  patch.append_child("TagList");
  addText(patch, "QuadVertexSortOrder", "RowMajor");
  addText(patch, "GeometryType", "QuadList");
  addText(patch, "Local2Global", formatMatrix(info.local2global));
  addText(patch, "LocalBoundingBox", formatBox(info.localBox));
  addText(patch, "GlobalBoundingBox", formatBox(info.globalBox));
  addText(patch, "Positions", info.positionsFile);
  if (!info.textureFile.empty()) {
    addText(patch.append_child("Coordinates"), "DiffuseColor1Coordinates", info.coordinatesFile);
    addText(patch.append_child("Textures"), "DiffuseColor1Texture", info.textureFile);
  } else {
    patch.append_child("Textures");
  }
  pugi::xml_node vsm = patch.append_child("Vsm");
  addText(vsm, "Key", info.key.toString());
  addText(vsm, "GridSize", std::to_string(grid.size()));
  addText(vsm, "Offset", "[" + std::to_string(r.x0) + ", " + std::to_string(r.y0) + "]");
  addText(vsm, "Resolution", formatDouble(info.resolution));
  addText(vsm, "Version", std::to_string(info.version));
  const fs::path xmlFile = folderDir / "Patch.xml";
  writeFile(xmlFile, bytesOf(xmlText(doc)));
}

fs::path OpcWriter::imagesLayerDir() {
  const fs::path layer = dir_.parent_path() / "Images" / std::string(kTextureLayer);
  std::lock_guard lock(imagesMutex_);
  if (!imagesCreated_) {
    std::error_code ec;
    for (const fs::path& d : {layer.parent_path(), layer}) {
      const bool created = fs::create_directory(d, ec);
      if (ec) {
        throw Error(ErrorCode::Io, "cannot create '" + d.string() + "': " + ec.message());
      }
      if (created) {
        if (durability_ == Durability::EachFile) {
          fsyncPath(d.parent_path(), true);
        } else {
          unsynced_ = true;
        }
      }
    }
    imagesCreated_ = true;
  }
  return layer;
}

void OpcWriter::removePatchFiles(const PatchInfo& info) {
  std::error_code ec;
  fs::remove_all(dir_ / info.folder, ec);
  if (!info.textureFile.empty()) {
    fs::remove(dir_.parent_path() / "Images" / std::string(kTextureLayer) / (info.folder + ".tif"),
               ec);
  }
}

void OpcWriter::writeHierarchy(const Model& model) {
  if (model.empty()) {
    throw Error(ErrorCode::InvalidArgument, "cannot write the hierarchy of an empty model");
  }
  pugi::xml_document doc;
  pugi::xml_node decl = doc.append_child(pugi::node_declaration);
  decl.append_attribute("version") = "1.0";
  decl.append_attribute("encoding") = "utf-8";
  pugi::xml_node hierarchy = doc.append_child("Aardvark").append_child("PatchHierarchy");
  hierarchy.append_child("TagList");
  std::string sizes = "[";
  for (const double size : model.avgGeometrySizes()) {
    sizes += (sizes.size() > 1 ? ", " : "") + formatDouble(size);
  }
  addText(hierarchy, "AvgGeometrySizes", sizes + "]");
  const PatchInfo& root = model.at(PatchKey::root());
  addText(hierarchy, "RootPatch", root.folder.empty() ? root.key.toString() : root.folder);
  pugi::xml_node map = hierarchy.append_child("SubPatchMap");
  for (const auto& [key, info] : model.patches()) {
    if (info.isLeaf()) {
      continue;
    }
    pugi::xml_node item = map.append_child("item");
    addText(item, "key", info.folder.empty() ? key.toString() : info.folder);
    pugi::xml_node val = item.append_child("val");
    for (const Quadrant q : kQuadrants) {
      if (info.hasChild(q)) {
        const PatchInfo& child = model.at(key.child(q));
        addText(val, std::string(toString(q)).c_str(),
                child.folder.empty() ? child.key.toString() : child.folder);
      }
    }
  }
  pugi::xml_node vsm = hierarchy.append_child("Vsm");
  addText(vsm, "GridSize", std::to_string(model.gridSize()));
  addText(vsm, "FormatVersion", "1");
  writeFile(dir_ / "patchhierarchy.xml", bytesOf(xmlText(doc)));
  // Another reader's cache of the old hierarchy would hide this one from it.
  while (const auto cache = detail::findEntry(dir_, "hierarchy.cache")) {
    std::error_code ec;
    if (!fs::remove(*cache, ec) || ec) {
      throw Error(ErrorCode::Io, "cannot remove stale '" + cache->string() + "'");
    }
  }
}

namespace {

/// Writes `bytes` to `fd`, opened with O_DIRECT: the whole blocks from an aligned copy, straight
/// to the device, then (O_DIRECT cleared) the rest through the page cache. 0 or the errno of the
/// failure; `refused` is set when the file system refuses direct writes (nothing was written).
int writeDirect(int fd, std::span<const std::byte> bytes, bool& refused) {
  const std::size_t whole = bytes.size() / kDirectBlock * kDirectBlock;
  const std::byte* aligned = bytes.data();
  if (reinterpret_cast<std::uintptr_t>(aligned) % kDirectBlock != 0) {
    std::byte* copy = directBuffer(whole);
    std::memcpy(copy, bytes.data(), whole);
    aligned = copy;
  }
  std::size_t done = 0;
  while (done < whole) {
    const ssize_t n = ::write(fd, aligned + done, whole - done);
    if (n < 0) {
      if (errno == EINTR) {
        continue;
      }
      if (errno == EINVAL && done == 0) {
        refused = true;
        break;
      }
      return errno;
    }
    done += static_cast<std::size_t>(n);
    if (done % kDirectBlock != 0) {
      break;  // a short write off the block grid: the rest goes through the page cache
    }
  }
  const int flags = ::fcntl(fd, F_GETFL);
  if (flags < 0 || ::fcntl(fd, F_SETFL, flags & ~O_DIRECT) != 0) {
    return errno;
  }
  return writeAll(fd, bytes.subspan(done));
}

}  // namespace

void OpcWriter::writeFile(const fs::path& file, std::span<const std::byte> bytes) {
  if (durability_ == Durability::EachFile) {
    writeAtomically(file, bytes);
    return;
  }
  // Deferred files are made durable by one syncfs before anything names them: large ones go to
  // the device directly, which saves copying them into the page cache and writing them back from
  // there (an import is mostly such files), and leaves the cache to what others read.
  const bool direct = bytes.size() >= kDirectMinimum && directWrites_.load();
  int fd = ::open(file.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC | (direct ? O_DIRECT : 0),
                  0644);
  if (fd < 0 && direct && errno == EINVAL) {  // no O_DIRECT on this file system (tmpfs)
    directWrites_ = false;
    fd = ::open(file.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  }
  if (fd < 0) {
    throwIoError("cannot create", file.string(), errno);
  }
  int errnum = 0;
  if (direct && directWrites_.load()) {
    bool refused = false;
    errnum = writeDirect(fd, bytes, refused);
    if (refused) {
      directWrites_ = false;
    }
  } else {
    errnum = writeAll(fd, bytes);
  }
  if (::close(fd) != 0 || errnum != 0) {
    throwIoError("cannot write", file.string(), errnum != 0 ? errnum : errno);
  }
  unsynced_ = true;
}

void OpcWriter::sync() {
  if (unsynced_) {
    syncFileSystem(dir_);
    unsynced_ = false;
  }
}

void syncFileSystem(const fs::path& dir) {
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) {
    throwIoError("cannot open for syncfs", dir.string(), errno);
  }
  if (::syncfs(fd) != 0) {
    const int errnum = errno;
    ::close(fd);
    throwIoError("cannot syncfs", dir.string(), errnum);
  }
  ::close(fd);
}

}  // namespace vsm::core
