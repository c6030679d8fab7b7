// Reading OPC directories: the hierarchy, every Patch.xml and the patches' vertex data.
#include "core/opc/opc_reader.hpp"

#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <deque>
#include <pugixml.hpp>
#include <set>
#include <span>

#include "core/common/error.hpp"
#include "core/common/numbers.hpp"
#include "core/common/random.hpp"
#include "core/common/text.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/opc_detail.hpp"
#include "core/opc/opc_index.hpp"

namespace vsm::core {
namespace fs = std::filesystem;

namespace {

constexpr std::string_view kHiddenPrefix = "vsm-hidden-";
constexpr std::string_view kHiddenSuffix = ".xml";

[[noreturn]] void corrupt(const fs::path& where, const std::string& message) {
  throw Error(ErrorCode::Corrupt, where.string() + ": " + message);
}

/// The child element called `name` in any letter case (exact spelling first).
pugi::xml_node childCi(const pugi::xml_node& node, std::string_view name) {
  if (pugi::xml_node exact = node.child(std::string(name).c_str())) {
    return exact;
  }
  for (pugi::xml_node child : node.children()) {
    if (child.type() == pugi::node_element && detail::equalsIgnoreCase(child.name(), name)) {
      return child;
    }
  }
  return {};
}

std::string textOf(const pugi::xml_node& node) {
  return std::string(trim(node.child_value()));
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

bool isPowerOfTwoPlusOne(long long n) {
  return n >= 3 && ((n - 1) & (n - 2)) == 0;
}

// ---- reading ---------------------------------------------------------------------------------

struct ParsedPatch {
  PatchInfo info;
  detail::PatchDetails details;
  std::optional<int> gridSize;  // from the extension
  std::optional<std::pair<int, int>> offset;
};

/// Reads one Patch.xml. Grid-size dependent fields (stored rectangle) are completed by the caller.
ParsedPatch readPatchXml(const fs::path& folderDir) {
  ParsedPatch parsed;
  PatchInfo& info = parsed.info;
  detail::PatchDetails& details = parsed.details;
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
    Mat4d local2global;
    std::copy(v.begin(), v.end(), local2global.m.begin());
    if (!local2global.isAffineInvertible()) {
      corrupt(*xmlFile, "<Local2Global> is not an invertible affine transform");
    }
    info.setLocal2Global(local2global);
  }
  const pugi::xml_node global = childCi(patch, "GlobalBoundingBox");
  const pugi::xml_node local = childCi(patch, "LocalBoundingBox");
  if (global && local) {
    info.globalBox = boxOf(numbersOf(global, 6, *xmlFile));
    info.localBox = boxOf(numbersOf(local, 6, *xmlFile));
  } else {
    details.boxesFromData = true;
  }
  PatchFiles files;
  if (const pugi::xml_node positions = childCi(patch, "Positions")) {
    files.positions = textOf(positions);
  }
  if (!detail::isSafeName(files.positions)) {
    corrupt(*xmlFile, "positions file name '" + files.positions + "' leaves its folder");
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
      files.coordinates = name;
    }
  }
  if (const pugi::xml_node textures = childCi(patch, "Textures")) {
    for (pugi::xml_node entry : textures.children()) {
      if (entry.type() == pugi::node_element) {
        const std::string name = textOf(entry);
        if (detail::isSafeTexturePath(name)) {
          files.texture = name;
        }
        break;
      }
    }
  }
  info.setFiles(std::move(files));
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
  char buffer[PatchKey::kMaxText];
  return detail::entryPath(detail::entryPath(patchesDir, info.folder(buffer)),
                           info.positionsFile());
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
    PatchGrid grid(gridSize, info.local2global());
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
  Mat4d l2g = info.local2global();
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

namespace detail {

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

namespace {

/// What a hierarchy file says, before any Patch.xml is read.
struct ParsedHierarchy {
  std::vector<double> avgSizes;
  std::string rootFolder;
  /// Parent folder -> child folder per quadrant.
  std::map<std::string, std::array<std::string, 4>> subPatches;
  std::optional<int> gridSize;
  bool hasExtension = false;
  std::optional<RevisionRecord> revision;
  /// The second hierarchy file (<Vsm><HiddenLevels>), when there is one, and the parents whose
  /// items it holds (their children are hidden).
  std::optional<fs::path> hiddenFile;
  std::set<std::string> hiddenParents;
};

/// The <item> elements of `subPatchMap` (in `file`) into `parsed`; `hidden`: they are the second
/// hierarchy file's.
void readItems(const fs::path& file, const pugi::xml_node& subPatchMap, bool hidden,
               ParsedHierarchy& parsed) {
  for (pugi::xml_node item : subPatchMap.children()) {
    if (item.type() != pugi::node_element || !equalsIgnoreCase(item.name(), "item")) {
      continue;
    }
    const std::string key = textOf(childCi(item, "key"));
    if (!isSafeName(key)) {
      corrupt(file, "patch name '" + key + "' is not a plain folder name");
    }
    std::array<std::string, 4> children;
    const pugi::xml_node val = childCi(item, "val");
    for (const Quadrant q : kQuadrants) {
      if (const pugi::xml_node child = childCi(val, toString(q))) {
        const std::string name = textOf(child);
        if (!isSafeName(name)) {
          corrupt(file, "patch name '" + name + "' is not a plain folder name");
        }
        children[static_cast<int>(q)] = name;
      }
    }
    if (!parsed.subPatches.emplace(key, children).second) {
      corrupt(file, "patch '" + key + "' has two <item> entries");
    }
    if (hidden) {
      parsed.hiddenParents.insert(key);
    }
  }
}

std::uint64_t revisionNumber(const fs::path& file, const pugi::xml_node& node,
                             std::string_view name) {
  const pugi::xml_node element = childCi(node, name);
  if (!element) {
    return 0;
  }
  const auto n = parseInteger(textOf(element));
  if (!n || *n < 0) {
    corrupt(file,
            "<Revision><" + std::string(name) + "> is not a count: '" + textOf(element) + "'");
  }
  return static_cast<std::uint64_t>(*n);
}

ParsedHierarchy parseHierarchy(const fs::path& file, bool withHidden = true) {
  const pugi::xml_document doc = parseXml(file);
  const pugi::xml_node hierarchy = childCi(childCi(doc, "Aardvark"), "PatchHierarchy");
  if (!hierarchy) {
    corrupt(file, "no <Aardvark><PatchHierarchy> element");
  }
  ParsedHierarchy parsed;
  if (const pugi::xml_node sizes = childCi(hierarchy, "AvgGeometrySizes")) {
    const auto values = parseNumberList(textOf(sizes));
    if (!values) {
      corrupt(file, "<AvgGeometrySizes> is not a list of numbers");
    }
    parsed.avgSizes = *values;
  }
  parsed.rootFolder = textOf(childCi(hierarchy, "RootPatch"));
  if (parsed.rootFolder.empty()) {
    corrupt(file, "no <RootPatch>");
  }
  readItems(file, childCi(hierarchy, "SubPatchMap"), false, parsed);
  if (!isSafeName(parsed.rootFolder)) {
    corrupt(file, "patch name '" + parsed.rootFolder + "' is not a plain folder name");
  }
  const pugi::xml_node vsm = childCi(hierarchy, "Vsm");
  parsed.hasExtension = static_cast<bool>(vsm);
  if (const pugi::xml_node size = childCi(vsm, "GridSize")) {
    const auto n = parseInteger(textOf(size));
    if (!n || !isPowerOfTwoPlusOne(*n) || *n > 32769) {
      corrupt(file, "<GridSize> must be 2^n+1, not '" + textOf(size) + "'");
    }
    parsed.gridSize = static_cast<int>(*n);
  }
  if (const pugi::xml_node revision = childCi(vsm, "Revision")) {
    RevisionRecord record;
    record.parent = revisionNumber(file, revision, "Parent");
    record.time = textOf(childCi(revision, "Time"));
    record.job = textOf(childCi(revision, "Job"));
    record.changed = revisionNumber(file, revision, "Changed");
    record.removed = revisionNumber(file, revision, "Removed");
    record.restoredFrom = revisionNumber(file, revision, "RestoredFrom");
    record.nonce = textOf(childCi(revision, "Nonce"));
    if (record.nonce.size() > 64) {
      corrupt(file, "<Nonce> is longer than 64 characters");
    }
    if (const pugi::xml_node fence = childCi(revision, "Fence")) {
      FencingToken token;
      token.takeover = revisionNumber(file, fence, "Takeover");
      const std::string lease = textOf(childCi(fence, "Lease"));
      const auto n = parseInteger(lease);
      if (token.takeover == 0 || !n || *n <= 0) {
        corrupt(file, "<Revision><Fence> needs a <Takeover> and a <Lease> above 0, not '" +
                          textOf(childCi(fence, "Takeover")) + "' and '" + lease + "'");
      }
      token.lease = *n;
      record.fence = token;
    }
    parsed.revision = std::move(record);
  }
  if (const pugi::xml_node hidden = childCi(vsm, "HiddenLevels"); hidden && withHidden) {
    const std::string name = textOf(hidden);
    if (!isHiddenHierarchyFileName(name)) {
      corrupt(file, "<HiddenLevels> names '" + name + "', not a file vsm-hidden-<hex>.xml");
    }
    const fs::path hiddenFile = file.parent_path() / name;
    std::error_code ec;
    if (!fs::is_regular_file(hiddenFile, ec)) {
      corrupt(file, "<HiddenLevels> names '" + name + "', which is missing");
    }
    const pugi::xml_document hiddenDoc = parseXml(hiddenFile);
    const pugi::xml_node levels = childCi(childCi(hiddenDoc, "Aardvark"), "VsmHiddenLevels");
    if (!levels) {
      corrupt(hiddenFile, "no <Aardvark><VsmHiddenLevels> element");
    }
    readItems(hiddenFile, childCi(levels, "SubPatchMap"), true, parsed);
    parsed.hiddenFile = hiddenFile;
  }
  return parsed;
}

}  // namespace

OpcContents readOpc(const fs::path& dir, std::string_view hierarchyName, bool withHidden) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) {
    throw Error(ErrorCode::NotFound, "no OPC at '" + dir.string() + "' (not a directory)");
  }
  const fs::path patchesDir = patchesDirOf(dir);
  const auto hierarchyFile = findEntry(patchesDir, hierarchyName);
  if (!hierarchyFile) {
    throw Error(ErrorCode::NotFound,
                "no OPC at '" + dir.string() + "' (no Patches/" + std::string(hierarchyName) + ")");
  }
  ParsedHierarchy hierarchy = parseHierarchy(*hierarchyFile, withHidden);
  const std::vector<double>& avgSizes = hierarchy.avgSizes;
  const std::string& rootFolder = hierarchy.rootFolder;
  const auto& subPatches = hierarchy.subPatches;

  // Walk from the root; keys come from the position in the tree.
  std::vector<std::pair<PatchKey, ParsedPatch>> parsed;
  std::set<std::string> seen;
  struct Queued {
    PatchKey key;
    std::string folder;
    bool hidden;
  };
  std::deque<Queued> queue{{PatchKey::root(), rootFolder, false}};
  while (!queue.empty()) {
    auto [key, folder, hidden] = queue.front();
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
    ParsedPatch patch = readPatchXml(*folderDir);
    patch.info.key = key;
    patch.info.setFolder(folder);
    patch.info.hidden = hidden;
    if (const auto it = subPatches.find(folder); it != subPatches.end()) {
      // A hidden patch's children are hidden too: its item must be the second file's.
      const bool hiddenChildren = hierarchy.hiddenParents.count(folder) != 0;
      if (hidden && !hiddenChildren) {
        corrupt(*hierarchyFile,
                "patch '" + folder + "' is a hidden level's, but its <item> is in this file");
      }
      for (const Quadrant q : kQuadrants) {
        const std::string& child = it->second[static_cast<int>(q)];
        if (!child.empty()) {
          if (key.depth >= PatchKey::kMaxDepth) {
            corrupt(*hierarchyFile, "the hierarchy is deeper than " +
                                        std::to_string(PatchKey::kMaxDepth) + " levels");
          }
          queue.push_back({key.child(q), child, hiddenChildren});
        }
      }
    }
    parsed.emplace_back(key, std::move(patch));
  }

  // The grid size: our extensions when present, else the root's stored positions.
  std::optional<int> gridSize = hierarchy.gridSize;
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
                       hierarchy.hiddenFile,
                       avgSizes,
                       hierarchy.hasExtension,
                       hierarchy.revision,
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
      const GridRect stored{x0, y0, x0 + header.sizes[0], y0 + header.sizes[1]};
      if (stored.x1 > *gridSize || stored.y1 > *gridSize || stored.empty()) {
        corrupt(file, "positions of " + std::to_string(header.sizes[0]) + " x " +
                          std::to_string(header.sizes[1]) + " at offset " + std::to_string(x0) +
                          ", " + std::to_string(y0) + " do not fit a " + std::to_string(*gridSize) +
                          " grid");
      }
      info.stored = stored;
    } else {
      info.stored = GridRect{0, 0, *gridSize, *gridSize};
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

fs::path patchesDirOf(const fs::path& dir) {
  const auto found = detail::findEntry(dir, "Patches");
  std::error_code ec;
  if (!found || !fs::is_directory(*found, ec)) {
    throw Error(ErrorCode::NotFound, "no OPC at '" + dir.string() + "' (no Patches directory)");
  }
  return *found;
}

std::optional<HierarchyStamp> hierarchyStamp(const fs::path& dir) {
  const auto patches = detail::findEntry(dir, "Patches");
  const auto file = patches ? detail::findEntry(*patches, "patchhierarchy.xml") : std::nullopt;
  struct stat st {};
  if (!file || ::stat(file->c_str(), &st) != 0) {
    return std::nullopt;
  }
  return HierarchyStamp{static_cast<std::uint64_t>(st.st_dev),
                        static_cast<std::uint64_t>(st.st_ino),
                        static_cast<std::uint64_t>(st.st_size),
                        std::int64_t{st.st_mtim.tv_sec} * 1'000'000'000 + st.st_mtim.tv_nsec};
}

Model readOpcModel(const fs::path& dir) {
  if (std::optional<OpcRevision> indexed = readOpcIndex(dir)) {
    return std::move(indexed->model);
  }
  return std::move(detail::readOpc(dir).model);
}

OpcRevision readOpcRevision(const fs::path& dir, std::string_view hierarchyName,
                            IndexBaseMemo* memo) {
  if (std::optional<OpcRevision> indexed = readOpcIndex(dir, hierarchyName, memo)) {
    return std::move(*indexed);
  }
  detail::OpcContents contents = detail::readOpc(dir, hierarchyName);
  return {std::move(contents.model), std::move(contents.revision)};
}

std::optional<RevisionRecord> readRevisionRecord(const fs::path& hierarchyFile) {
  return detail::parseHierarchy(hierarchyFile, false).revision;
}

std::string hiddenHierarchyFileName() {
  return std::string(kHiddenPrefix) + randomHex() + randomHex() + std::string(kHiddenSuffix);
}

std::optional<std::string> hiddenHierarchyNamedBy(const fs::path& hierarchyFile) {
  constexpr std::size_t kTail = 4096;
  int fd = -1;
  try {
    fd = detail::openForReading(hierarchyFile);
  } catch (const Error& e) {
    if (e.code() == ErrorCode::NotFound) {
      return std::nullopt;  // no such hierarchy: it names nothing
    }
    throw;
  }
  std::string tail;
  try {
    struct stat st {};
    if (::fstat(fd, &st) != 0) {
      throwIoError("cannot stat", hierarchyFile.string(), errno);
    }
    const auto size = static_cast<std::size_t>(st.st_size);
    const std::size_t from = size > kTail ? size - kTail : 0;
    tail.resize(size - from);
    tail.resize(detail::readAt(fd, from,
                               std::as_writable_bytes(std::span(tail.data(), tail.size())),
                               hierarchyFile.string()));
  } catch (...) {
    ::close(fd);
    throw;
  }
  ::close(fd);
  constexpr std::string_view open = "<HiddenLevels>";
  const std::size_t at = tail.rfind(open);
  const std::size_t end = at == std::string::npos ? at : tail.find("</HiddenLevels>", at);
  if (end == std::string::npos) {
    return std::nullopt;
  }
  std::string name = tail.substr(at + open.size(), end - at - open.size());
  return isHiddenHierarchyFileName(name) ? std::optional(std::move(name)) : std::nullopt;
}

bool isHiddenHierarchyFileName(std::string_view name) {
  if (!name.starts_with(kHiddenPrefix) || !name.ends_with(kHiddenSuffix)) {
    return false;
  }
  const std::string_view digits =
      name.substr(kHiddenPrefix.size(), name.size() - kHiddenPrefix.size() - kHiddenSuffix.size());
  return digits.size() == 16 && std::all_of(digits.begin(), digits.end(), [](char c) {
           return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f');
         });
}

void forEachNamedFolder(const fs::path& hierarchyFile,
                        const std::function<void(std::string_view)>& fn) {
  if (forEachIndexedFolder(hierarchyFile, fn)) {
    return;
  }
  const detail::ParsedHierarchy parsed = detail::parseHierarchy(hierarchyFile);
  fn(parsed.rootFolder);
  for (const auto& [folder, children] : parsed.subPatches) {
    fn(folder);
    for (const std::string& child : children) {
      if (!child.empty()) {
        fn(child);
      }
    }
  }
}

PatchGrid readPatchGrid(const fs::path& dir, const Model& model, const PatchInfo& info) {
  const fs::path file = positionsPath(patchesDirOf(dir), info);
  return gridFromArray(readAaraFile(file), model.gridSize(), info, file);
}

}  // namespace vsm::core
