#pragma once

#include <atomic>
#include <filesystem>
#include <mutex>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "core/common/progress.hpp"
#include "core/grid/texture_tile.hpp"
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

/// Reads one patch's vertex data into a full gridSize x gridSize grid (cropped borders restored as
/// undefined). V3d files are re-based on their own centre so float32 keeps precision; the returned
/// grid's local2global() is then the patch's Local2Global times that translation.
/// Throws Error(NotFound / Io / Corrupt).
PatchGrid readPatchGrid(const std::filesystem::path& dir, const Model& model,
                        const PatchInfo& info);

/// Writes patches and the hierarchy of one OPC directory in the standard layout (`Patches/`,
/// `Patch.xml`, `Positions.aara`, `patchhierarchy.xml`) plus vsm's extension elements.
///
/// Durability::EachFile, for a directory others read: every file is written to a temporary name
/// in its directory, fsynced and renamed into place, and the directory fsynced, so a crash leaves
/// the old file or the new one. Durability::Deferred, for a private staging directory its owner
/// publishes as a whole (an import): files are written in place and nothing is fsynced until
/// sync(), which the owner calls once before it publishes (far fewer creates and disk flushes);
/// files of 64 KiB and more go to the device with O_DIRECT (no copy in the page cache) where the
/// file system allows it.
///
/// writePatch() may run concurrently for different patches; writeHierarchy() and sync() run
/// after them, from one thread.
class OpcWriter {
 public:
  enum class Durability { EachFile, Deferred };

  /// Creates `dir`/Patches when missing.
  OpcWriter(std::filesystem::path dir, Durability durability);

  /// Writes all files of one patch (never one alone) into Patches/<info.folder>/, cropping
  /// undefined border rows and columns, and updates `info` from `grid` (boxes, Local2Global,
  /// resolution, stored rectangle) as Model::describe does: the boxes hold the grid's defined
  /// vertices and `childrenBox`, the union of the children's global boxes (empty for a leaf).
  /// An empty info.folder becomes info.key.toString(). Precondition: grid.anyDefined().
  ///
  /// A textured patch (info.textureFile names the tile writeTexture() wrote for this folder, before
  /// or after this call) also gets Coordinates.aara (V2f per stored vertex, see
  /// textureCoordinates) in its folder, and Patch.xml names both in <Coordinates> and <Textures>
  /// (OPC.md); info.coordinatesFile says so. Throws Error(InvalidArgument) when info.textureFile
  /// names any other file (a texture this writer did not write).
  void writePatch(PatchInfo& info, const PatchGrid& grid, Box3d childrenBox);

  /// Writes the texture tile of a patch as Images/Diffuse/<folder>.tif (RGBA 8-bit TIFF) and sets
  /// info.textureFile to name it (an empty info.folder becomes info.key.toString()).
  void writeTexture(PatchInfo& info, const TextureTile& tile);

  /// Removes every file writePatch wrote for `info` (its folder and its texture tile), ignoring
  /// errors: for a builder discarding a subtree of its own staging directory.
  void removePatchFiles(const PatchInfo& info);

  /// Writes Patches/patchhierarchy.xml atomically; call after every patch it names is written.
  /// Removes a stale `hierarchy.cache` of other readers.
  void writeHierarchy(const Model& model);

  /// Makes everything written so far durable (Deferred durability): one syncfs of the file
  /// system holding the directory.
  void sync();

 private:
  /// Writes one file as the durability says.
  void writeFile(const std::filesystem::path& file, std::span<const std::byte> bytes);
  /// Images/<layer>/, created (once, under imagesMutex_) on first use.
  std::filesystem::path imagesLayerDir();

  std::filesystem::path dir_;
  Durability durability_;
  std::atomic<bool> unsynced_{false};     // Deferred: something written since the last sync()
  std::atomic<bool> directWrites_{true};  // Deferred: large files with O_DIRECT (see writeFile)
  std::mutex imagesMutex_;                // guards imagesCreated_ (writePatch runs concurrently)
  bool imagesCreated_ = false;
};

/// The Patch.xml texture entry (relative to Images/) of the tile OpcWriter::writeTexture writes
/// for a patch folder: "Diffuse\\<folder>.tif".
std::string textureEntryFor(std::string_view folder);

/// Makes every file written so far on the file system holding `dir` durable: one syncfs (a single
/// journal commit, where fsyncing thousands of files costs one each). Throws Error(Io).
void syncFileSystem(const std::filesystem::path& dir);

/// One finding of validateOpc: where (a file or patch) and what is wrong.
struct Finding {
  std::string where;
  std::string message;
};

/// Checks every invariant of the model and the format: the hierarchy is a tree whose folders
/// exist; each .aara decodes with the right type and size; stored boxes contain exactly the
/// vertices (within float32 rounding); parents' boxes contain their children's; every defined
/// parent vertex equals the child vertex it was reduced from (within the float32 rounding of both
/// patches' stored coordinates); resolutions match; AvgGeometrySizes has enough entries and
/// realistic values; no stale hierarchy.cache. Returns all findings; empty when valid.
std::vector<Finding> validateOpc(const std::filesystem::path& dir, Progress* progress = nullptr);

}  // namespace vsm::core
