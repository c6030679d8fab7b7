#pragma once

#include <cstdint>
#include <filesystem>
#include <functional>
#include <optional>
#include <set>
#include <string>
#include <string_view>

#include "core/pyramid/model.hpp"

namespace vsm::core {

/// Reads an OPC directory's metadata: Patches/patchhierarchy.xml and every patch's Patch.xml
/// (no vertex data), or vsm's index of the hierarchy (opc_index.hpp) when it has a current one:
/// then no Patch.xml is read. Lenient as OPC.md says: either letter case for file and folder names,
/// optional elements missing, V3d positions, foreign folder names (keys are assigned by position in
/// the quadtree, the root being 0_0_0). Our extension elements are used when present, never
/// required.
///
/// Throws Error(NotFound) when `dir` holds no hierarchy, Error(Corrupt) with a one-line message on
/// malformed XML, a hierarchy naming a missing folder, a cycle or a patch reached twice, a folder
/// name containing "..", "/" or "\\", a bad number, or grids of differing sizes.
Model readOpcModel(const std::filesystem::path& dir);

/// The fencing token of the writer that published a revision (<Vsm><Revision><Fence>): in a
/// cluster, the etcd revision at which that writer's node claimed the model (`takeover`: greater
/// for every later claim, by any node) and the etcd lease it claimed it under. A revision with an
/// older takeover than one already seen was committed by a writer that had lost the model, so
/// followers refuse it and a writer does not commit over a newer one. Tokens compare by takeover.
struct FencingToken {
  std::uint64_t takeover = 0;
  std::int64_t lease = 0;
  friend bool operator==(const FencingToken&, const FencingToken&) = default;
};

/// What vsm records about a revision in the hierarchy that publishes it (<Vsm><Revision>, an
/// extension other readers ignore): the revision it was made from, when (UTC, ISO 8601), by which
/// job, how many patches it added or replaced and removed, and the revision it restored if any. Its
/// number is the model version the hierarchy describes (the newest patch version).
struct RevisionRecord {
  std::uint64_t parent = 0;  // 0: none (an import)
  std::string time;
  std::string job;
  std::uint64_t changed = 0;
  std::uint64_t removed = 0;
  std::uint64_t restoredFrom = 0;  // the revision whose content it restored; 0: none
  /// Random per publish (8 hex digits; empty in records written before it existed): the same
  /// number published twice (the first lost in a power cut after it was served) never has the
  /// same record, so tags derived from it never repeat.
  std::string nonce;
  /// The publishing writer's token; nullopt when it had none (a single node, the CLI, records
  /// written before tokens existed).
  std::optional<FencingToken> fence;
};

/// How many revisions a publish keeps by default, the new one included (core/store).
inline constexpr unsigned kDefaultKeepRevisions = 8;

class IndexBaseMemo;  // opc_index.hpp

/// The model one hierarchy file of `dir` describes (Patches/`hierarchyName`: the current one, or a
/// kept revision's) with its revision record when it has one; from its index when current, as
/// readOpcModel, and a delta index's base from `memo` as readOpcIndex. Throws as readOpcModel.
struct OpcRevision {
  OpcRevision(Model m, std::optional<RevisionRecord> r,
              std::optional<std::uint64_t> d = std::nullopt)
      : model(std::move(m)), record(std::move(r)), digest(d) {}

  Model model;
  std::optional<RevisionRecord> record;
  /// modelDigest(model) when the reader knew it by the change (a delta applied to a base whose
  /// digest `memo` kept); nullopt: not computed.
  std::optional<std::uint64_t> digest;
};
OpcRevision readOpcRevision(const std::filesystem::path& dir,
                            std::string_view hierarchyName = "patchhierarchy.xml",
                            IndexBaseMemo* memo = nullptr);

/// The revision record of one hierarchy file, read from that file alone; nullopt when it has none.
/// Throws Error(NotFound / Io / Corrupt) as readOpcModel.
std::optional<RevisionRecord> readRevisionRecord(const std::filesystem::path& hierarchyFile);

/// A set of patch folder names, searchable by string_view.
using FolderSet = std::set<std::string, std::less<>>;

/// Calls `fn` with each patch folder a hierarchy file names (its root and every SubPatchMap entry),
/// at least once each, in no particular order: from its index when it has a current one, else
/// from the file alone. Throws Error(NotFound / Io / Corrupt) as readOpcModel.
void forEachNamedFolder(const std::filesystem::path& hierarchyFile,
                        const std::function<void(std::string_view)>& fn);

/// A new name for a model's second hierarchy file, which names its hidden levels
/// (core/opc/README.md, "Hidden levels"): "vsm-hidden-<16 hex digits>.xml", random, so that a file
/// once written is never replaced in place.
std::string hiddenHierarchyFileName();

/// True for a name hiddenHierarchyFileName gives.
bool isHiddenHierarchyFileName(std::string_view name);

/// The second hierarchy file a hierarchy file of vsm's names (<Vsm><HiddenLevels>), read from its
/// last 4 kB, where vsm writes its elements (a few kB whatever the model's size); nullopt when it
/// names none there or does not exist. For removing files no hierarchy names any more, not for
/// reading a model (readOpcModel follows the element wherever it is). Throws Error(Io /
/// Unavailable) when it cannot be read: a file a hierarchy still names is never taken for unnamed.
std::optional<std::string> hiddenHierarchyNamedBy(const std::filesystem::path& hierarchyFile);

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
