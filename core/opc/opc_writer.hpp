#pragma once

#include <filesystem>
#include <memory>
#include <mutex>
#include <set>
#include <span>
#include <string>
#include <string_view>
#include <unordered_map>
#include <utility>
#include <vector>

#include "core/durable/durable_io.hpp"
#include "core/grid/texture_tile.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

/// Writes patches and the hierarchy of one OPC directory in the standard layout (`Patches/`,
/// `Patch.xml`, `Positions.aara`, `patchhierarchy.xml`) plus vsm's extension elements.
///
/// All file writes go through core/durable. Durability::EachFile, for a directory others read:
/// every file is replaced atomically and durably (durable::writeFileAtomically), directories
/// created are synced. Durability::Deferred, for files nobody reads until their owner publishes
/// them (an import's staging directory, an edit's draft folders): files are written in place
/// (durable::DraftWriter) and made durable by the owner's durable::FileSystemSync, which the owner
/// creates before the first write and syncs once before anything names the files.
///
/// writePatch() may run concurrently for different patches; the hierarchy is written after them,
/// from one thread.
class OpcWriter {
 public:
  enum class Durability { EachFile, Deferred };

  /// Creates `dir`/Patches when missing.
  OpcWriter(std::filesystem::path dir, Durability durability);

  /// Writes all files of one patch (never one alone) into Patches/<info.folder()>/, cropping
  /// undefined border rows and columns, and updates `info` from `grid` (boxes, Local2Global,
  /// resolution, stored rectangle) as Model::describe does: the boxes hold the grid's defined
  /// vertices and `childrenBox`, the union of the children's global boxes (empty for a leaf).
  /// Precondition: grid.anyDefined().
  ///
  /// A textured patch (info.textureFile() names the tile writeTexture() wrote for this folder,
  /// before or after this call) also gets Coordinates.aara (V2f per stored vertex, see
  /// textureCoordinates) in its folder, and Patch.xml names both in <Coordinates> and <Textures>
  /// (OPC.md); info.coordinatesFile() says so. Throws Error(InvalidArgument) when
  /// info.textureFile() names any other file (a texture this writer did not write).
  void writePatch(PatchInfo& info, const PatchGrid& grid, Box3d childrenBox);

  /// Writes the texture tile of a patch as Images/Diffuse/<folder>.tif (RGBA 8-bit TIFF) and sets
  /// info.textureFile() to name it.
  void writeTexture(PatchInfo& info, const TextureTile& tile);

  /// Removes every file writePatch wrote for `info` (its folder and its texture tile), ignoring
  /// errors: for a builder discarding a subtree of its own staging directory.
  void removePatchFiles(const PatchInfo& info);

  /// Writes Patches/patchhierarchy.xml; call after every patch it names is written (and, with
  /// Deferred durability, made durable). EachFile: stageHierarchy, commit, finishHierarchy.
  /// Deferred: in place, for a directory published as a whole afterwards.
  void writeHierarchy(const Model& model);

 private:
  /// Writes one file as the durability says.
  void writeFile(const std::filesystem::path& file, std::span<const std::byte> bytes);
  /// Writes the texture coordinates of a patch of `gridSize` storing `stored` to `file`. With
  /// deferred durability, a patch stored whole (nearly all of them) gets a hard link to the OPC's
  /// one file of those coordinates, `.vsm-shared/coordinates-<size>.aara` at its root (written
  /// once, atomically, and never again): an import writes them once, not once per patch. Cropped
  /// patches, whose rectangles vary, get their own file.
  void writeCoordinates(const std::filesystem::path& file, int gridSize, const GridRect& stored);
  /// Images/<layer>/, created (once, under imagesMutex_) on first use.
  std::filesystem::path imagesLayerDir();

  std::filesystem::path dir_;
  Durability durability_;
  durable::DraftWriter drafts_;  // Deferred durability
  std::mutex imagesMutex_;       // guards imagesCreated_ (writePatch runs concurrently)
  bool imagesCreated_ = false;
  std::mutex sharedMutex_;             // guards sharedFiles_
  std::set<std::string> sharedFiles_;  // the shared files known to hold what their names say
};

/// The hierarchy text of a model's runs (Model::runs) as the last hierarchy written through it laid
/// them out, so that the next one regenerates only the runs a change touched: a run's <item>
/// elements are reused while the run and every run holding its patches' children are the ones it
/// was made from (a publish of a small merge into 10^6 patches generates a few runs of its 60 MB).
/// Holds the text and the runs of the last hierarchy written, no others. Thread-safe.
class HierarchyMemo {
 public:
  /// The <item> elements of `model`'s patches with children (SubPatchMap's content at nesting
  /// `depth`) in key order, in pieces to be written one after the other (none empty), taken from
  /// what it holds where it can; keeps what it hands out.
  std::vector<std::shared_ptr<const std::string>> items(const Model& model, std::size_t depth);
  /// Bytes of text held.
  std::size_t bytes() const;
  /// The runs the last items() took as held, and all it handed out.
  std::pair<std::size_t, std::size_t> lastReused() const;

 private:
  struct Run {
    std::shared_ptr<const void> id;
    std::vector<std::shared_ptr<const void>> childRuns;
    std::shared_ptr<const std::string> text;
  };
  mutable std::mutex mutex_;
  std::size_t depth_ = 0;  // the nesting the text was made at
  std::size_t lastReused_ = 0;
  std::unordered_map<const void*, Run> runs_;
};

/// The hierarchy of the OPC at `dir` written and fsynced under a temporary name beside
/// Patches/patchhierarchy.xml; its commit() (a rename) is the commit point of a new model version.
/// With `revision`, the hierarchy records it (<Vsm><Revision>); `fileName` names another hierarchy
/// file under Patches/ (a kept revision's). `memo`: the text of the hierarchy last written through
/// it, reused where the model's runs are the same (null: made anew). Throws
/// Error(InvalidArgument) for an empty model, Error(NotFound) without Patches/, Error(Io).
std::unique_ptr<durable::PendingFile> stageHierarchy(
    const std::filesystem::path& dir, const Model& model, const RevisionRecord* revision = nullptr,
    std::string_view fileName = "patchhierarchy.xml", HierarchyMemo* memo = nullptr);

/// What follows a committed hierarchy: syncs Patches/ (making the rename durable) and removes a
/// stale `hierarchy.cache` of other readers. Idempotent: the next open retries it after a
/// failure. Throws Error(Io).
void finishHierarchy(const std::filesystem::path& dir);

/// The Patch.xml texture entry (relative to Images/) of the tile OpcWriter::writeTexture writes
/// for a patch folder: "Diffuse\\<folder>.tif".
std::string textureEntryFor(std::string_view folder);

}  // namespace vsm::core
