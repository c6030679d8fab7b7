#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "core/durable/durable_io.hpp"
#include "core/opc/opc_reader.hpp"

namespace vsm::core {

/// vsm's index of one hierarchy file (core/opc/README.md, "The index"): every PatchInfo field a
/// full read derives from the hierarchy and the Patch.xml files (key, folder, boxes, Local2Global,
/// resolution, version, stored rectangle, file names) and the revision record, in one binary file
/// beside the hierarchy, `Patches/<stem>.vsmidx` ("patchhierarchy.vsmidx",
/// "vsm-revision-7.vsmidx"). It records the stamp (inode, size, modification time) of the
/// hierarchy file it describes and is used only while that file has the same stamp: a hierarchy
/// replaced by anyone (a publish, another tool, a copy) makes it stale, never wrong. Other
/// readers ignore it.

/// "patchhierarchy.xml" -> "patchhierarchy.vsmidx".
std::string indexFileName(std::string_view hierarchyName);

/// True for a file name indexFileName gives.
bool isIndexFileName(std::string_view name);

/// The stamp of one file (its device, inode, size, modification time). Throws Error(Io).
HierarchyStamp fileStamp(const std::filesystem::path& file);

/// The bytes of the index of `model` (with `record`) for a hierarchy file of stamp `stamp`.
std::vector<std::byte> encodeOpcIndex(const HierarchyStamp& stamp, const Model& model,
                                      const RevisionRecord* record);

/// The checksum that ends the index's summary and the index: 64 bits over 8-byte words, the tail
/// zero-padded (core/opc/README.md, "The index").
std::uint64_t opcIndexChecksum(std::span<const std::byte> bytes);

/// The model and record of the index bytes if they describe a hierarchy of `stamp`; nullopt when
/// they describe another stamp or are malformed (truncated, checksum, unknown format).
std::optional<OpcRevision> decodeOpcIndex(std::span<const std::byte> bytes,
                                          const HierarchyStamp& stamp);

/// Calls `fn` with the folder of each patch of the hierarchy file `hierarchyFile`, from its index
/// beside it (in key order), when it has a current one, and returns true; false when it has none
/// (`fn` may have been called for some folders when the index ends early).
bool forEachIndexedFolder(const std::filesystem::path& hierarchyFile,
                          const std::function<void(std::string_view)>& fn);

/// What `vsm info` prints of a model, from the head of its index alone (a few kB read).
struct OpcSummary {
  int gridSize = 0;
  std::uint64_t patches = 0;
  Box3d bounds;  // the root's
  std::vector<LevelSummary> levels;
};

/// The summary of the current hierarchy of `dir` when it has a current index; nullopt otherwise.
std::optional<OpcSummary> readOpcIndexSummary(const std::filesystem::path& dir);

/// The hierarchy `hierarchyName` of `dir` from its index, when it has a current one; nullopt when
/// there is none, it is stale or unreadable (the caller reads the hierarchy in full).
std::optional<OpcRevision> readOpcIndex(const std::filesystem::path& dir,
                                        std::string_view hierarchyName = "patchhierarchy.xml");

/// The index of the hierarchy file `hierarchyFile` (committed, or staged under its temporary name:
/// the stamp survives the rename) staged as Patches/indexFileName(`hierarchyName`) of `dir`: the
/// caller commits it (a rename) before the hierarchy's commit and syncs Patches/ after both.
/// Throws Error(Io).
std::unique_ptr<durable::PendingFile> stageOpcIndex(const std::filesystem::path& dir,
                                                    std::string_view hierarchyName,
                                                    const std::filesystem::path& hierarchyFile,
                                                    const Model& model,
                                                    const RevisionRecord* record);

/// Reads the hierarchy `hierarchyName` of `dir` in full and writes its index, atomically and
/// durably (`vsm index`); returns the number of patches. Throws as readOpcRevision and Error(Io),
/// Error(Conflict) when the hierarchy changed during the read.
std::size_t writeOpcIndex(const std::filesystem::path& dir,
                          std::string_view hierarchyName = "patchhierarchy.xml");

}  // namespace vsm::core
