#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>

#include "core/pyramid/model.hpp"

namespace vsm::core {

/// Reads an OPC directory's metadata: Patches/patchhierarchy.xml and every patch's Patch.xml
/// (no vertex data). Lenient as OPC.md says: either letter case for file and folder names,
/// optional elements missing, V3d positions, foreign folder names (keys are assigned by position in
/// the quadtree, the root being 0_0_0). Our extension elements are used when present, never
/// required.
///
/// Throws Error(NotFound) when `dir` holds no hierarchy, Error(Corrupt) with a one-line message on
/// malformed XML, a hierarchy naming a missing folder, a cycle or a patch reached twice, a folder
/// name containing "..", "/" or "\\", a bad number, or grids of differing sizes.
Model readOpcModel(const std::filesystem::path& dir);

/// `dir`/Patches in whatever letter case it exists. Throws Error(NotFound) when there is none.
std::filesystem::path patchesDirOf(const std::filesystem::path& dir);

/// Which version of the hierarchy file `dir` holds now: its inode, size and modification time. A
/// publish replaces the file by a rename, so a new version has another stamp. Empty when there is
/// no hierarchy file (or it cannot be read).
struct HierarchyStamp {
  std::uint64_t device = 0, inode = 0, size = 0;
  std::int64_t modifiedNs = 0;
  friend bool operator==(const HierarchyStamp&, const HierarchyStamp&) = default;
};
std::optional<HierarchyStamp> hierarchyStamp(const std::filesystem::path& dir);

/// Reads one patch's vertex data into a full gridSize x gridSize grid (cropped borders restored as
/// undefined). V3d files are re-based on their own centre so float32 keeps precision; the returned
/// grid's local2global() is then the patch's Local2Global times that translation.
/// Throws Error(NotFound / Io / Corrupt).
PatchGrid readPatchGrid(const std::filesystem::path& dir, const Model& model,
                        const PatchInfo& info);

}  // namespace vsm::core
