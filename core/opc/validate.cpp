#include <algorithm>
#include <cmath>
#include <cstring>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>

#include "core/common/error.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/opc_detail.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/validate.hpp"

namespace vsm::core {
namespace fs = std::filesystem;

namespace {

double distance(const Vec3d& a, const Vec3d& b) {
  return (a - b).norm();
}

/// Largest distance between corresponding faces of two boxes.
double faceDistance(const Box3d& a, const Box3d& b) {
  return std::max({std::abs(a.min.x - b.min.x), std::abs(a.min.y - b.min.y),
                   std::abs(a.min.z - b.min.z), std::abs(a.max.x - b.max.x),
                   std::abs(a.max.y - b.max.y), std::abs(a.max.z - b.max.z)});
}

double magnitude(const Box3d& box) {
  return std::max({std::abs(box.min.x), std::abs(box.min.y), std::abs(box.min.z),
                   std::abs(box.max.x), std::abs(box.max.y), std::abs(box.max.z)});
}

class Validator {
 public:
  Validator(detail::OpcContents contents, const fs::path& dir, Progress* progress)
      : c_(std::move(contents)), dir_(dir), progress_(progress) {}

  std::vector<Finding> run() {
    checkHierarchy();
    const std::size_t total = c_.model.patchCount();
    std::size_t done = 0;
    for (const auto& [key, info] : c_.model.patches()) {
      checkPatch(key, info);
      if (!info.isLeaf()) {
        checkReduction(key, info);
      }
      // Hold at most one family at a time (children are read again on their own turn).
      grids_.clear();
      if (progress_ != nullptr) {
        progress_->report("validating", static_cast<double>(++done) / total);
      }
    }
    checkAvgGeometrySizes();
    return std::move(findings_);
  }

 private:
  void add(std::string where, std::string message) {
    findings_.push_back({std::move(where), std::move(message)});
  }
  std::string where(const PatchInfo& info) const { return "Patches/" + info.folder(); }

  /// The patch's grid, read once; null (with a finding) when it cannot be read.
  const PatchGrid* grid(const PatchInfo& info) {
    auto it = grids_.find(info.key);
    if (it == grids_.end()) {
      std::shared_ptr<const PatchGrid> grid;
      try {
        grid = std::make_shared<const PatchGrid>(readPatchGrid(dir_, c_.model, info));
      } catch (const Error& e) {
        if (unreadable_.insert(info.key).second) {
          add(where(info), e.what());
        }
      }
      it = grids_.emplace(info.key, std::move(grid)).first;
    }
    return it->second.get();
  }

  void checkHierarchy() {
    for (const std::string& folder : c_.unreachableItems) {
      add(c_.hierarchyFile.string(), "<item> for '" + folder + "' is not reachable from the root");
    }
    if (c_.hiddenFile) {
      checkVisibleView();
    }
    for (const fs::path& cache : c_.hierarchyCaches) {
      add(cache.string(), "another reader's hierarchy.cache would hide patchhierarchy.xml");
    }
  }

  /// With hidden levels: what other OPC readers see, the hierarchy file alone, is a whole model
  /// by itself, and exactly the patches that are not hidden.
  void checkVisibleView() {
    const std::string where = c_.hierarchyFile.string();
    try {
      const detail::OpcContents visible =
          detail::readOpc(dir_, c_.hierarchyFile.filename().string(), false);
      for (const std::string& folder : visible.unreachableItems) {
        add(where, "<item> for '" + folder + "' is not reachable from the root without " +
                       c_.hiddenFile->filename().string());
      }
      std::size_t seen = 0;
      for (const auto& [key, info] : c_.model.patches()) {
        const PatchInfo* alone = visible.model.find(key);
        seen += alone != nullptr ? 1 : 0;
        if ((alone != nullptr) == info.hidden) {
          add(where, "patch " + key.toString() + " is " + (info.hidden ? "hidden" : "visible") +
                         " but " + (alone != nullptr ? "" : "not ") +
                         "in the hierarchy other OPC readers see");
        }
      }
      if (seen != visible.model.patchCount()) {
        add(where, "names patches the full hierarchy does not reach");
      }
    } catch (const Error& e) {
      add(where, std::string("the hierarchy other OPC readers see, without the hidden levels, "
                             "is not a model: ") +
                     e.what());
    }
  }

  void checkPatch(const PatchKey& key, const PatchInfo& info) {
    const detail::PatchDetails& details = c_.patches.at(key);
    for (const std::string& element : details.missingElements) {
      add(where(info), "Patch.xml lacks <" + element + ">, which other OPC readers require");
    }
    if (details.geometryType != "QuadList" &&
        std::find(details.missingElements.begin(), details.missingElements.end(), "GeometryType") ==
            details.missingElements.end()) {
      add(where(info), "GeometryType is '" + details.geometryType + "', not QuadList");
    }
    if (details.extensionKey && *details.extensionKey != key.toString()) {
      add(where(info), "<Vsm><Key> says " + *details.extensionKey + " but the patch sits at " +
                           key.toString() + " in the hierarchy");
    }
    checkTexture(info);
    const PatchGrid* g = grid(info);
    if (g == nullptr) {
      return;
    }
    if (!g->anyDefined()) {
      add(where(info), "no defined vertex");
      return;
    }
    if (details.hasExtension && g->definedRect() != info.stored) {
      add(where(info), "stored positions have undefined border rows or columns left uncropped");
    }
    // Boxes hold the defined vertices and the children's boxes (OPC.md), and nothing more.
    const Box3d children = c_.model.childrenBox(key);
    const double tolerance = 2 * detail::roundingOf(*g) + 1e-9 * magnitude(info.globalBox);
    if (!details.boxesFromData) {
      Box3d globalBox = g->globalBox();
      globalBox.extend(children);
      const double offBy = faceDistance(globalBox, info.globalBox);
      if (offBy > tolerance) {
        add(where(info), "GlobalBoundingBox differs from the box of its vertices and children by " +
                             std::to_string(offBy) + " m");
      }
      // A V3d patch was re-based when read: its file's local frame is info.local2global()'s.
      Box3d localBox = g->local2global() == info.local2global()
                           ? g->localBox()
                           : transformBox(info.local2global().inverse(), g->globalBox());
      localBox.extend(transformBox(info.local2global().inverse(), children));
      const double localTolerance =
          std::ldexp(g->maxAbsLocal(), -22) + 1e-9 * magnitude(localBox) + 1e-12;
      const double localOff = faceDistance(localBox, info.localBox);
      if (localOff > localTolerance) {
        add(where(info), "LocalBoundingBox differs from the box of its vertices and children by " +
                             std::to_string(localOff));
      }
    }
    if (details.extensionResolution) {
      const double actual = g->resolution();
      if (std::abs(actual - *details.extensionResolution) > 1e-6 * std::max(actual, 1.0)) {
        add(where(info), "<Vsm><Resolution> is " + std::to_string(*details.extensionResolution) +
                             " but the vertices give " + std::to_string(actual));
      }
    }
    measured_[key.depth].first += g->resolution();
    measured_[key.depth].second += 1;
  }

  /// A textured patch: its coordinates decode as V2f (V2d) of the stored positions' size with
  /// finite values, and its texture file exists under Images/.
  void checkTexture(const PatchInfo& info) {
    if (info.textureFile().empty()) {
      if (!info.coordinatesFile().empty()) {
        add(where(info),
            "<Coordinates> names " + info.coordinatesFile() + " but <Textures> is empty");
      }
      return;
    }
    if (!detail::findTextureFile(dir_, info.textureFile())) {
      add(where(info), "texture '" + info.textureFile() + "' does not exist under Images/");
    }
    if (info.coordinatesFile().empty()) {
      add(where(info), "has a texture but no <Coordinates><DiffuseColor1Coordinates>");
      return;
    }
    char buffer[PatchKey::kMaxText];
    const fs::path file = detail::entryPath(detail::entryPath(c_.patchesDir, info.folder(buffer)),
                                            info.coordinatesFile());
    AaraArray coordinates;
    try {
      coordinates = readAaraFile(file);
    } catch (const Error& e) {
      add(where(info), e.what());
      return;
    }
    if (coordinates.type != AaraType::V2f && coordinates.type != AaraType::V2d) {
      add(where(info), info.coordinatesFile() + " holds " +
                           std::string(toString(coordinates.type)) + ", not V2f");
      return;
    }
    const GridRect& r = info.stored;
    if (coordinates.sizes.size() != 2 || coordinates.sizes[0] != r.width() ||
        coordinates.sizes[1] != r.height()) {
      add(where(info), info.coordinatesFile() + " does not have the stored positions' size " +
                           std::to_string(r.width()) + " x " + std::to_string(r.height()));
      return;
    }
    if (coordinates.type == AaraType::V2f) {
      const std::size_t count = coordinates.elementCount() * 2;
      for (std::size_t i = 0; i < count; ++i) {
        float v = 0;
        std::memcpy(&v, coordinates.data.data() + i * 4, 4);
        if (!std::isfinite(v)) {
          add(where(info), info.coordinatesFile() + " holds a coordinate that is not finite");
          break;
        }
      }
    }
  }

  /// Every defined parent vertex must be the child vertex it was reduced from.
  void checkReduction(const PatchKey& key, const PatchInfo& info) {
    const PatchGrid* parent = grid(info);
    if (parent == nullptr) {
      return;
    }
    std::array<const PatchGrid*, 4> children{};
    std::array<bool, 4> unreadable{};  // reported already; their area cannot be checked
    for (const Quadrant q : kQuadrants) {
      if (info.hasChild(q)) {
        children[static_cast<int>(q)] = grid(c_.model.at(key.child(q)));
        unreadable[static_cast<int>(q)] = children[static_cast<int>(q)] == nullptr;
      }
    }
    const int s = c_.model.gridSize();
    const int half = s - 1;
    // Float32 rounding of each grid's stored coordinates, computed once per grid.
    const double parentRounding = detail::roundingOf(*parent);
    std::array<double, 4> childRounding{};
    for (int q = 0; q < 4; ++q) {
      childRounding[q] = children[q] != nullptr ? detail::roundingOf(*children[q]) : 0.0;
    }
    std::size_t wrong = 0;
    std::size_t missing = 0;
    double worst = 0;
    int worstX = 0;
    int worstY = 0;
    for (int py = 0; py < s; ++py) {
      for (int px = 0; px < s; ++px) {
        const int ux = 2 * px;
        const int uy = 2 * py;
        // The child vertex this parent vertex comes from: first present child defining it.
        const PatchGrid* source = nullptr;
        double sourceRounding = 0;
        int cx = 0;
        int cy = 0;
        bool unknown = false;
        for (const Quadrant q : kQuadrants) {
          const PatchGrid* child = children[static_cast<int>(q)];
          const int ox = (static_cast<int>(q) & 1) * half;
          const int oy = (static_cast<int>(q) >> 1) * half;
          if (ux < ox || ux > ox + half || uy < oy || uy > oy + half) {
            continue;
          }
          if (unreadable[static_cast<int>(q)]) {
            unknown = true;
            break;
          }
          if (child == nullptr) {
            continue;
          }
          if (child->defined(ux - ox, uy - oy)) {
            source = child;
            sourceRounding = childRounding[static_cast<int>(q)];
            cx = ux - ox;
            cy = uy - oy;
            break;
          }
        }
        if (unknown) {
          continue;
        }
        const bool defined = parent->defined(px, py);
        if (source == nullptr) {
          if (defined) {
            ++wrong;
          }
          continue;
        }
        if (!defined) {
          ++missing;
          continue;
        }
        const double off = distance(parent->global(px, py), source->global(cx, cy));
        const double tolerance =
            parentRounding + sourceRounding + 1e-12 * source->global(cx, cy).norm();
        if (off > tolerance) {
          ++wrong;
          if (off > worst) {
            worst = off;
            worstX = px;
            worstY = py;
          }
        }
      }
    }
    if (wrong > 0) {
      add(where(info), std::to_string(wrong) +
                           " vertices are not the child vertices they reduce (worst " +
                           std::to_string(worst) + " m at " + std::to_string(worstX) + ", " +
                           std::to_string(worstY) + ")");
    }
    if (missing > 0) {
      add(where(info),
          std::to_string(missing) + " vertices are undefined where a child defines them");
    }
  }

  void checkAvgGeometrySizes() {
    const std::vector<double>& sizes = c_.avgGeometrySizes;
    // The levels OPC readers see: hidden levels are not theirs.
    const int depth = deepestVisibleDepth(c_.model.levels());
    const std::string where = c_.hierarchyFile.string();
    if (sizes.size() < static_cast<std::size_t>(depth + 1)) {
      add(where, "AvgGeometrySizes has " + std::to_string(sizes.size()) +
                     " entries; the deepest leaf OPC readers see needs " +
                     std::to_string(depth + 1));
      return;
    }
    for (int d = 0; d <= depth; ++d) {
      const double value = sizes[sizes.size() - 1 - static_cast<std::size_t>(d)];
      if (!std::isfinite(value) || value <= 0) {
        add(where, "AvgGeometrySizes entry for depth " + std::to_string(d) + " is " +
                       std::to_string(value));
        continue;
      }
      const auto it = measured_.find(d);
      if (it == measured_.end() || it->second.second == 0 || it->second.first <= 0) {
        continue;
      }
      const double mean = it->second.first / static_cast<double>(it->second.second);
      if (value < 0.5 * mean || value > 2 * mean) {
        add(where, "AvgGeometrySizes gives " + std::to_string(value) + " m for depth " +
                       std::to_string(d) + " but its meshes measure " + std::to_string(mean) +
                       " m");
      }
    }
  }

  detail::OpcContents c_;
  fs::path dir_;
  Progress* progress_;
  std::vector<Finding> findings_;
  std::map<PatchKey, std::shared_ptr<const PatchGrid>> grids_;
  std::set<PatchKey> unreadable_;
  /// Per depth: sum of patch resolutions and how many patches measured.
  std::map<int, std::pair<double, std::size_t>> measured_;
};

}  // namespace

std::vector<Finding> validateOpc(const fs::path& dir, Progress* progress) {
  std::optional<detail::OpcContents> contents;
  try {
    contents.emplace(detail::readOpc(dir));
  } catch (const Error& e) {
    return {{dir.string(), e.what()}};
  }
  return Validator(std::move(*contents), dir, progress).run();
}

}  // namespace vsm::core
