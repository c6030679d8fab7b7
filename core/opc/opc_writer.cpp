// Writing OPC directories: patches, texture tiles and the hierarchy, through the durable-I/O
// module.
#include "core/opc/opc_writer.hpp"

#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <cstring>
#include <limits>
#include <optional>
#include <string_view>
#include <unordered_set>
#include <utility>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/numbers.hpp"
#include "core/common/random.hpp"
#include "core/durable/durable_io.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/opc_detail.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/texture_file.hpp"
#include "core/opc/xml_writer.hpp"

namespace vsm::core {
namespace fs = std::filesystem;

namespace {

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

std::span<const std::byte> bytesOf(const std::string& text) {
  return {reinterpret_cast<const std::byte*>(text.data()), text.size()};
}

/// Starts an OPC XML file as every one starts (<Aardvark>, `element`, <TagList />), `element`
/// left open.
detail::XmlWriter startAardvark(std::string_view element) {
  detail::XmlWriter xml;
  xml.open("Aardvark");
  xml.open(element);
  xml.empty("TagList");
  return xml;
}

}  // namespace

OpcWriter::OpcWriter(fs::path dir, Durability durability)
    : dir_(std::move(dir)), durability_(durability) {
  const bool sync = durability_ == Durability::EachFile;
  std::vector<fs::path> missing;  // dir_ and its missing ancestors, innermost first
  std::error_code ec;
  for (fs::path d = dir_; !d.empty() && !fs::exists(d, ec); d = d.parent_path()) {
    missing.push_back(d);
    if (d == d.parent_path()) {
      break;
    }
  }
  for (auto it = missing.rbegin(); it != missing.rend(); ++it) {
    durable::createDirectory(*it, sync);
  }
  if (const auto existing = detail::findEntry(dir_, "Patches")) {
    dir_ = *existing;
  } else {
    dir_ /= "Patches";
    durable::createDirectory(dir_, sync);
  }
}

namespace {

/// Checks that a patch's folder and positions file have plain names.
void checkNames(const PatchInfo& info) {
  if (!detail::isSafeName(info.folder()) || !detail::isSafeName(info.positionsFile())) {
    throw Error(ErrorCode::InvalidArgument,
                "patch folder '" + info.folder() + "' is not a plain name");
  }
}

}  // namespace

std::string textureEntryFor(std::string_view folder) {
  return std::string(kTextureLayer) + "\\" + std::string(folder) + ".tif";
}

void OpcWriter::writeTexture(PatchInfo& info, const TextureTile& tile) {
  checkNames(info);
  writeFile(imagesLayerDir() / (info.folder() + ".tif"), encodeTextureTiff(tile));
  PatchFiles files = info.files();
  files.texture = textureEntryFor(info.folder());
  info.setFiles(std::move(files));
}

void OpcWriter::writePatch(PatchInfo& info, const PatchGrid& grid, Box3d childrenBox) {
  // By value: callers may pass info.globalBox, which is overwritten below.
  if (!grid.anyDefined()) {
    throw Error(ErrorCode::InvalidArgument,
                "patch " + info.key.toString() + " has no defined vertex to write");
  }
  checkNames(info);
  if (!info.textureFile().empty() && info.textureFile() != textureEntryFor(info.folder())) {
    throw Error(ErrorCode::InvalidArgument, "patch " + info.folder() + " names texture '" +
                                                info.textureFile() +
                                                "', which this writer does not write");
  }
  const fs::path folderDir = dir_ / info.folder();
  durable::createDirectory(folderDir, durability_ == Durability::EachFile);

  const PatchGrid::Summary summary = grid.summarize();
  info.setLocal2Global(grid.local2global());
  info.localBox = summary.localBox;
  info.globalBox = grid.local2global().isTranslation()
                       ? transformBox(grid.local2global(), info.localBox)
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
  const std::span<std::byte> positions = durable::DraftWriter::threadBuffer(
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
  const fs::path positionsFile = folderDir / info.positionsFile();
  writeFile(positionsFile, positions);

  PatchFiles files = info.files();
  files.coordinates.clear();
  if (!files.texture.empty()) {
    // Texture coordinates of the stored vertices, before the Patch.xml naming them.
    files.coordinates = "Coordinates.aara";
    writeCoordinates(folderDir / files.coordinates, grid.size(), r);
  }
  info.setFiles(std::move(files));

  detail::XmlWriter xml = startAardvark("Patch");
  xml.text("QuadVertexSortOrder", "RowMajor");
  xml.text("GeometryType", "QuadList");
  xml.text("Local2Global", formatMatrix(info.local2global()));
  xml.text("LocalBoundingBox", formatBox(info.localBox));
  xml.text("GlobalBoundingBox", formatBox(info.globalBox));
  xml.text("Positions", info.positionsFile());
  if (!info.textureFile().empty()) {
    xml.open("Coordinates");
    xml.text("DiffuseColor1Coordinates", info.coordinatesFile());
    xml.close();
    xml.open("Textures");
    xml.text("DiffuseColor1Texture", info.textureFile());
    xml.close();
  } else {
    xml.empty("Textures");
  }
  xml.open("Vsm");
  xml.text("Key", info.key.toString());
  xml.text("GridSize", std::to_string(grid.size()));
  xml.text("Offset", "[" + std::to_string(r.x0) + ", " + std::to_string(r.y0) + "]");
  xml.text("Resolution", formatDouble(info.resolution));
  xml.text("Version", std::to_string(info.version));
  const fs::path xmlFile = folderDir / "Patch.xml";
  writeFile(xmlFile, bytesOf(std::move(xml).finish()));
}

fs::path OpcWriter::imagesLayerDir() {
  const fs::path layer = dir_.parent_path() / "Images" / std::string(kTextureLayer);
  std::lock_guard lock(imagesMutex_);
  if (!imagesCreated_) {
    for (const fs::path& d : {layer.parent_path(), layer}) {
      durable::createDirectory(d, durability_ == Durability::EachFile);
    }
    imagesCreated_ = true;
  }
  return layer;
}

void OpcWriter::removePatchFiles(const PatchInfo& info) {
  std::error_code ec;
  fs::remove_all(dir_ / info.folder(), ec);
  if (!info.textureFile().empty()) {
    fs::remove(
        dir_.parent_path() / "Images" / std::string(kTextureLayer) / (info.folder() + ".tif"), ec);
  }
}

namespace {

/// The <item> element of `info`, a patch with children, as OPC.md writes it; the ids of the runs
/// that hold its children added to `childRuns` when given.
void writeItem(detail::XmlWriter& xml, const Model& model, const PatchKey& key,
               const PatchInfo& info, std::vector<std::shared_ptr<const void>>* childRuns) {
  xml.open("item", true);
  xml.text("key", info.folder());
  xml.open("val");
  for (const Quadrant q : kQuadrants) {
    if (info.hasChild(q)) {
      const PatchKey child = key.child(q);
      xml.text(toString(q), model.at(child).folder());
      if (childRuns != nullptr) {
        std::shared_ptr<const void> holder = model.runOf(child);
        if (childRuns->empty() || childRuns->back() != holder) {
          childRuns->push_back(std::move(holder));
        }
      }
    }
  }
  xml.close();
  xml.close();
}

/// The second hierarchy file of a model with hidden levels (core/opc/README.md, "Hidden levels"):
/// the <item> elements of every patch whose children are hidden, in key order. Its name is new
/// for every file written (never replaced in place: the hierarchy naming it is the commit point).
struct HiddenHierarchy {
  std::string name;
  std::string text;
};

HiddenHierarchy hiddenHierarchyXml(const Model& model) {
  detail::XmlWriter xml = startAardvark("VsmHiddenLevels");
  xml.open("SubPatchMap");
  for (const auto& [key, info] : model.patches()) {
    if (model.childrenHidden(key)) {
      writeItem(xml, model, key, info, nullptr);
    }
  }
  xml.close();
  return {hiddenHierarchyFileName(), std::move(xml).finish()};
}

/// The <item> elements of the patches with children in `run`, made at nesting `depth`, with the
/// ids of the runs that hold their children added to `childRuns`.
std::string runItems(const Model& model, const Model::Run& run, std::size_t depth,
                     std::vector<std::shared_ptr<const void>>& childRuns) {
  detail::XmlWriter xml(depth);
  for (auto it = run.begin; it != run.end; ++it) {
    const auto [key, info] = *it;
    if (!info.isLeaf() && !model.childrenHidden(key)) {
      writeItem(xml, model, key, info, &childRuns);
    }
  }
  return std::move(xml).finish();
}

/// A hierarchy document in pieces: its start, SubPatchMap's items (the memo's text, not copied:
/// 60 MB at 10^6 patches), its end.
struct HierarchyText {
  std::string head;
  std::vector<std::shared_ptr<const std::string>> items;
  std::string tail;
  /// The second hierarchy file this one names, when the model has hidden levels.
  std::optional<HiddenHierarchy> hidden;

  std::vector<std::span<const std::byte>> pieces() const {
    std::vector<std::span<const std::byte>> all{bytesOf(head)};
    for (const auto& item : items) {
      all.push_back(bytesOf(*item));
    }
    all.push_back(bytesOf(tail));
    return all;
  }
  std::string joined() const {
    std::string all = head;
    for (const auto& item : items) {
      all += *item;
    }
    return all + tail;
  }
};

HierarchyText hierarchyXml(const Model& model, const RevisionRecord* revision,
                           HierarchyMemo* memo) {
  if (model.empty()) {
    throw Error(ErrorCode::InvalidArgument, "cannot write the hierarchy of an empty model");
  }
  HierarchyText text;
  // The levels OPC readers see: down to the deepest holding a patch that is not hidden.
  const std::vector<LevelSummary> levels = model.levels();
  const auto visibleLevels = static_cast<std::size_t>(deepestVisibleDepth(levels)) + 1;
  if (anyHidden(levels)) {
    text.hidden = hiddenHierarchyXml(model);
  }
  detail::XmlWriter xml = startAardvark("PatchHierarchy");
  std::string sizes = "[";
  const std::vector<double> allSizes = model.avgGeometrySizes();  // the deepest level's first
  for (std::size_t i = allSizes.size() - visibleLevels; i < allSizes.size(); ++i) {
    sizes += (sizes.size() > 1 ? ", " : "") + formatDouble(allSizes[i]);
  }
  xml.text("AvgGeometrySizes", sizes + "]");
  xml.text("RootPatch", model.at(PatchKey::root()).folder());
  xml.open("SubPatchMap");
  text.items =
      memo != nullptr ? memo->items(model, xml.depth()) : HierarchyMemo().items(model, xml.depth());
  if (!text.items.empty()) {
    text.head = xml.cut();
  }
  xml.close();
  xml.open("Vsm");
  xml.text("GridSize", std::to_string(model.gridSize()));
  xml.text("FormatVersion", "1");
  if (text.hidden) {
    xml.text("HiddenLevels", text.hidden->name);
  }
  if (revision != nullptr) {
    xml.open("Revision");
    xml.text("Parent", std::to_string(revision->parent));
    xml.text("Time", revision->time);
    xml.text("Job", revision->job);
    xml.text("Changed", std::to_string(revision->changed));
    xml.text("Removed", std::to_string(revision->removed));
    if (revision->restoredFrom != 0) {
      xml.text("RestoredFrom", std::to_string(revision->restoredFrom));
    }
    if (!revision->nonce.empty()) {
      xml.text("Nonce", revision->nonce);
    }
    if (const auto& token = revision->fence) {
      xml.open("Fence");
      xml.text("Takeover", std::to_string(token->takeover));
      xml.text("Lease", std::to_string(token->lease));
      xml.close();
    }
    xml.close();
  }
  (text.items.empty() ? text.head : text.tail) = std::move(xml).finish();
  return text;
}

}  // namespace

std::vector<std::shared_ptr<const std::string>> HierarchyMemo::items(const Model& model,
                                                                     std::size_t depth) {
  std::lock_guard lock(mutex_);
  if (depth != depth_) {
    runs_.clear();
    depth_ = depth;
  }
  const std::vector<Model::Run> runs = model.runs();
  std::unordered_set<const void*> present;
  present.reserve(runs.size());
  for (const Model::Run& run : runs) {
    present.insert(run.id.get());
  }
  // A run held is the same keys and nodes (Model::runs); a child run held is the same children,
  // so the same names under each <val>. The runs held keep their addresses from being reused.
  std::unordered_map<const void*, Run> kept;
  kept.reserve(runs.size());
  std::vector<std::shared_ptr<const std::string>> pieces;
  lastReused_ = 0;
  for (const Model::Run& run : runs) {
    const auto known = runs_.find(run.id.get());
    if (known != runs_.end() &&
        std::all_of(known->second.childRuns.begin(), known->second.childRuns.end(),
                    [&](const std::shared_ptr<const void>& c) { return present.count(c.get()); })) {
      ++lastReused_;
      if (!known->second.text->empty()) {
        pieces.push_back(known->second.text);
      }
      kept.emplace(run.id.get(), std::move(known->second));
      continue;
    }
    Run made{run.id, {}, {}};
    made.text = std::make_shared<const std::string>(runItems(model, run, depth, made.childRuns));
    if (!made.text->empty()) {
      pieces.push_back(made.text);
    }
    kept.emplace(run.id.get(), std::move(made));
  }
  runs_ = std::move(kept);
  return pieces;
}

std::pair<std::size_t, std::size_t> HierarchyMemo::lastReused() const {
  std::lock_guard lock(mutex_);
  return {lastReused_, runs_.size()};
}

std::size_t HierarchyMemo::bytes() const {
  std::lock_guard lock(mutex_);
  std::size_t total = 0;
  for (const auto& [id, run] : runs_) {
    total += run.text->size();
  }
  return total;
}

std::unique_ptr<durable::PendingFile> stageHierarchy(const fs::path& dir, const Model& model,
                                                     const RevisionRecord* revision,
                                                     std::string_view fileName,
                                                     HierarchyMemo* memo) {
  const HierarchyText text = hierarchyXml(model, revision, memo);
  const fs::path patches = patchesDirOf(dir);
  if (text.hidden) {
    // Durable under its final name before the hierarchy naming it can be committed; until then
    // no hierarchy names it (a leftover after a crash: core/store's sweep removes it).
    durable::writeFileAtomically(patches / text.hidden->name, bytesOf(text.hidden->text));
  }
  return std::make_unique<durable::PendingFile>(patches / fileName, text.pieces());
}

void finishHierarchy(const fs::path& dir) {
  const fs::path patches = patchesDirOf(dir);
  durable::syncDirectory(patches);
  // Another reader's cache of the old hierarchy would hide this one from it. Removed by the name
  // that reader writes (OPC.md), not searched for in any case: a case-insensitive search reads
  // the whole directory, a tenth of a merge's time at 10^5 patches.
  const fs::path cache = patches / "hierarchy.cache";
  if (::unlink(cache.c_str()) != 0 && errno != ENOENT) {
    throwIoError("cannot remove stale", cache.string(), errno);
  }
}

void OpcWriter::writeHierarchy(const Model& model) {
  if (durability_ == Durability::EachFile) {
    stageHierarchy(dir_.parent_path(), model)->commit();
    finishHierarchy(dir_.parent_path());
  } else {
    const HierarchyText text = hierarchyXml(model, nullptr, nullptr);
    if (text.hidden) {
      writeFile(dir_ / text.hidden->name, bytesOf(text.hidden->text));
    }
    writeFile(dir_ / "patchhierarchy.xml", bytesOf(text.joined()));
  }
}

namespace {

/// Coordinates.aara of a patch of `gridSize` storing `stored`: V2f per stored vertex.
std::vector<std::byte> coordinatesAara(int gridSize, const GridRect& stored) {
  AaraArray coordinates;
  coordinates.type = AaraType::V2f;
  coordinates.sizes = {stored.width(), stored.height()};
  const std::vector<float> uvs =
      textureCoordinates(gridSize, stored.x0, stored.y0, stored.width(), stored.height());
  coordinates.data.resize(uvs.size() * sizeof(float));
  std::memcpy(coordinates.data.data(), uvs.data(), coordinates.data.size());
  return encodeAara(coordinates);
}

}  // namespace

void OpcWriter::writeCoordinates(const fs::path& file, int gridSize, const GridRect& stored) {
  if (durability_ == Durability::EachFile || stored != GridRect{0, 0, gridSize, gridSize}) {
    writeFile(file, coordinatesAara(gridSize, stored));
    return;
  }
  const fs::path sharedDir = dir_.parent_path() / ".vsm-shared";
  const std::string name = "coordinates-" + std::to_string(gridSize) + ".aara";
  const fs::path shared = sharedDir / name;
  {
    std::lock_guard lock(sharedMutex_);
    if (sharedFiles_.count(name) == 0) {
      // Left by an earlier writer: used when it holds exactly these bytes, else replaced (the
      // patches linked to the old one keep it).
      const std::vector<std::byte> bytes = coordinatesAara(gridSize, stored);
      std::vector<std::byte> existing;
      try {
        existing = detail::readFile(shared, bytes.size() + 1);
      } catch (const Error&) {
        // Missing or unreadable: written anew below.
      }
      if (existing != bytes) {
        durable::createDirectory(sharedDir, true);
        durable::writeFileAtomically(shared, bytes);
      }
      sharedFiles_.insert(name);
    }
  }
  if (!drafts_.link(shared, file)) {
    drafts_.write(file, coordinatesAara(gridSize, stored));
  }
}

void OpcWriter::writeFile(const fs::path& file, std::span<const std::byte> bytes) {
  if (durability_ == Durability::EachFile) {
    durable::writeFileAtomically(file, bytes);
  } else {
    drafts_.write(file, bytes);
  }
}

}  // namespace vsm::core
