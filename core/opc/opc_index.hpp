#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
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

/// A folder that a revision no longer names and its parent revision did: the folder of a patch it
/// replaced (in a new folder) or removed, with that patch's key.
struct RetiredFolder {
  PatchKey key;
  std::string folder;
  friend bool operator==(const RetiredFolder&, const RetiredFolder&) = default;
};

/// The bytes of the index of `model` (with `record`) for a hierarchy file of stamp `stamp`, with
/// the folders the revision retired from its parent (`record->parent`) when the caller knows them
/// (a publish does; null: not known, e.g. `vsm index`).
std::vector<std::byte> encodeOpcIndex(const HierarchyStamp& stamp, const Model& model,
                                      const RevisionRecord* record,
                                      const std::vector<RetiredFolder>* retired = nullptr);

/// What a delta index builds on: a full index in Patches/ (isIndexBaseFileName), its size and the
/// checksum it ends with.
struct IndexBase {
  std::string name;
  std::uint64_t size = 0;
  std::uint64_t checksum = 0;
};

/// True for the name of a base of delta indexes: "vsm-index-base-<...>.vsmidx", inside its
/// directory.
bool isIndexBaseFileName(std::string_view name);

/// The bytes of a delta index (format 3) of `model` for a hierarchy of `stamp`: the head of a full
/// index (summary, record, retired folders), then `base` and the patches that differ from it:
/// `changed` (in `model`, recorded whole) and `removed` (only their keys).
std::vector<std::byte> encodeOpcIndexDelta(const HierarchyStamp& stamp, const Model& model,
                                           const RevisionRecord* record,
                                           const std::vector<RetiredFolder>* retired,
                                           const IndexBase& base, const std::set<PatchKey>& changed,
                                           const std::set<PatchKey>& removed);

/// The model and record of delta bytes `delta` if they describe a hierarchy of `stamp` and `base`
/// is the base they name (its size and checksum), both whole; nullopt otherwise.
std::optional<OpcRevision> decodeOpcIndexDelta(std::span<const std::byte> delta,
                                               const HierarchyStamp& stamp,
                                               std::span<const std::byte> base);

/// The base the index file `index` builds on when it is a delta (read from its head, whatever
/// hierarchy it describes); nullopt for a full index, none, or an unreadable one.
std::optional<IndexBase> readIndexBase(const std::filesystem::path& index);

/// A publish writes a new base when the patches that differ from the current base would be more
/// than 1/kIndexDeltaShare of the model: a delta stays under ~1/8 of a full index, and a full one
/// is written once every many small publishes.
inline constexpr std::size_t kIndexDeltaShare = 8;

/// The index files of a publish: a new base (or none) and the index beside the hierarchy.
struct StagedIndex {
  /// A new base written whole; or null.
  std::unique_ptr<durable::PendingFile> base;
  /// Or the current index, a full one, that becomes the new base `adoptedAs` by a hard link (a
  /// copy where the file system has none); empty paths when not.
  std::filesystem::path adopted;
  std::filesystem::path adoptedAs;
  std::unique_ptr<durable::PendingFile> index;

  /// Puts the new base, if any, in place and syncs its directory: durable before `index`, which
  /// names it, is committed. Throws Error(Io).
  void commitBase() const;
};

/// Stages the index of the hierarchy `hierarchyFile` (staged under its temporary name: the stamp
/// survives the rename) that a publish is about to commit for `model`, as
/// Patches/patchhierarchy.vsmidx: a delta over the base the current index builds on (when it is a
/// delta describing `replaced`, the hierarchy the publish replaces, and its base is there), with
/// the patches that differ from that base (those it recorded, and `changed`, `removed`) while they
/// stay within 1/kIndexDeltaShare of the model. When the current index is a whole full index of
/// `replaced` (`vsm index`, a generator), it becomes the base Patches/`baseName` as it is, with a
/// delta of `changed` and `removed` (never larger than a new base): a million-patch model's first
/// publish writes no 250 MB base. Else a new base, Patches/`baseName` (a full index), and an
/// empty delta over it. The caller commits the base (commitBase) first, then the index just
/// before the hierarchy, and syncs Patches/ after both. Throws Error(Io).
StagedIndex stagePublishedIndex(
    const std::filesystem::path& dir, const std::filesystem::path& hierarchyFile,
    const Model& model, const RevisionRecord& record, const std::vector<RetiredFolder>& retired,
    const std::set<PatchKey>& changed, const std::set<PatchKey>& removed,
    const std::optional<HierarchyStamp>& replaced, const std::string& baseName);

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

/// What the head of a hierarchy file's index says of the revision, without its patches: the record
/// and, when the publish that wrote it knew them, the folders it retired from its parent.
struct IndexedRevision {
  std::optional<RevisionRecord> record;
  std::optional<std::vector<RetiredFolder>> retired;
};

/// The head of an index (its first bytes, or all of them) if it describes a hierarchy of `stamp`
/// and its own checksum holds (format 2 on); nullopt otherwise, also when `bytes` end before the
/// head does.
std::optional<IndexedRevision> decodeOpcIndexHead(std::span<const std::byte> bytes,
                                                  const HierarchyStamp& stamp);

/// The head of the index beside `hierarchyFile` (read up to its own checksum: a few kB after a
/// small merge) when it is current and of a format that has one; nullopt otherwise (none, stale,
/// unreadable, damaged, or written before heads had a checksum: the caller reads the hierarchy).
std::optional<IndexedRevision> readIndexedRevision(const std::filesystem::path& hierarchyFile);

/// The last base of delta indexes a reader decoded (or the full index it read, which the next
/// publish adopts as its base), kept so that the next index over the same base (a replica
/// following small publishes: LiveModel::reopen) decodes only its delta: its model is a copy of
/// the base's, sharing the base's chunks and nodes wherever the delta does not reach (so keeping
/// the base costs the patches its deltas replaced). Thread-safe.
class IndexBaseMemo {
 public:
  /// The model of `base` when it is the one kept (by size and checksum, whatever its name), with
  /// its modelDigest in `digest` (when not null); null otherwise.
  std::shared_ptr<const Model> find(const IndexBase& base, std::uint64_t* digest = nullptr) const;
  /// Keeps `model` as the model of `base`, in place of the one kept before, with its digest
  /// (modelDigest: computed here, once a base, so that each model read over it gets its own from
  /// the delta alone), which it returns.
  std::uint64_t keep(const IndexBase& base, std::shared_ptr<const Model> model);
  /// The model kept; null when none is.
  std::shared_ptr<const Model> model() const;

 private:
  mutable std::mutex mutex_;
  IndexBase base_;
  std::shared_ptr<const Model> model_;
  std::uint64_t digest_ = 0;
};

/// The hierarchy `hierarchyName` of `dir` from its index, when it has a current one; nullopt when
/// there is none, it is stale or unreadable (the caller reads the hierarchy in full). A delta's
/// base comes from `memo` when it holds it, and is kept there when read (null: no memo).
std::optional<OpcRevision> readOpcIndex(const std::filesystem::path& dir,
                                        std::string_view hierarchyName = "patchhierarchy.xml",
                                        IndexBaseMemo* memo = nullptr);

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
