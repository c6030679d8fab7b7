#pragma once

// Internal to core/store: how a model's files are named and found on disk, shared by the opening
// (leftover sweep), the revisions and the edit. Not installed, not included outside core/store.

#include <cstdint>
#include <ctime>
#include <filesystem>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <unordered_set>
#include <vector>

#include "core/opc/opc_reader.hpp"
#include "core/pyramid/patch_key.hpp"

namespace vsm::core {

struct ModelSnapshot;

namespace store {

/// Folder of a patch version written by an edit: "d_x_y-v<version>-<nonce>". Never the name of an
/// imported patch, so a crash leftover is recognisable (and removable) by its name alone; the
/// edit's nonce makes it differ from every folder an earlier edit of the same version wrote (one
/// lost in a power cut after it was served), so names and the tags made from them never repeat.
std::string draftFolder(const PatchKey& key, std::uint64_t version, std::string_view nonce);

/// Folders vsm names: "d_x_y" as an import writes them, "d_x_y-vN[-nonce]" as an edit does.
bool isOurFolderName(const std::string& name);

/// The folders a model names, without a set of all of them (1.4 million strings at 10^6 patches):
/// a folder named after its patch's key ("d_x_y", "d_x_y-vN-nonce", as vsm names them) is looked
/// up at that key; the others (a foreign OPC's names) are held in a set of their own. Valid while
/// the model is unchanged.
class NamedFolders {
 public:
  explicit NamedFolders(const Model& model);
  bool contains(std::string_view folder) const;
  /// Of `keys`, sorted and each the key of a folder named exactly as the key's text ("10_3_7"),
  /// those whose folder the model does not name: one pass over both in key order instead of a
  /// lookup a folder (the sweep's 1.4 million at 10^6 patches).
  std::vector<PatchKey> unnamed(const std::vector<PatchKey>& keys) const;
  /// The key of a folder named exactly as that key's text; nullopt for any other name.
  static std::optional<PatchKey> plainKey(std::string_view folder);

 private:
  /// Whether `folder` is named: by `atKey`, the patch at the key the name starts with (null for
  /// none), or by another patch (others_).
  bool names(const PatchInfo* atKey, std::string_view folder) const;

  const Model& model_;
  std::unordered_set<std::string> others_;
};

/// Texture tiles vsm names: "<one of our folder names>.tif" in Images/Diffuse/.
bool isOurTileName(const std::string& name);

/// The file of a tile OpcWriter::writeTexture wrote for `folder` under the model at `dir`.
std::filesystem::path ourTileFile(const std::filesystem::path& dir, const std::string& folder);

/// The revision a kept hierarchy file holds, from its name ("vsm-revision-<n>.xml", n of 1 to 19
/// digits); nullopt for any other name.
std::optional<std::uint64_t> revisionOfFile(std::string_view name);

/// The kept revision files under `patches` by revision number ("vsm-revision-<n>.xml").
std::map<std::uint64_t, std::filesystem::path> revisionFiles(const std::filesystem::path& patches);

/// Removes each second hierarchy file (hidden levels, core/opc/README.md) of `candidates` (names
/// under `patches`) that none of `hierarchies` names any more (hiddenHierarchyNamedBy), and syncs
/// `patches` after a removal. Returns how many it removed; a failed removal is logged (the next
/// open's sweep retries it). Throws Error(Io) when a hierarchy cannot be read, before removing
/// anything.
std::size_t removeUnnamedHiddenFiles(const std::filesystem::path& patches,
                                     const std::set<std::string>& candidates,
                                     const std::vector<std::filesystem::path>& hierarchies);

/// Now, UTC, ISO 8601 to the second.
std::string utcNow();

/// A time as utcNow() writes it ("2026-12-03T09:41:07Z"); nullopt for anything else.
std::optional<std::time_t> parseUtcTime(const std::string& text);

/// The modification time of `file`, UTC, ISO 8601; empty when it cannot be read.
std::string fileTime(const std::filesystem::path& file);

/// A snapshot of one revision read from its hierarchy (the current one or a kept file).
std::shared_ptr<ModelSnapshot> snapshotOf(OpcRevision read,
                                          const std::filesystem::path& hierarchyFile);

/// Removes patch folders (and the tiles vsm named for them) that no kept revision names any more.
/// Failures are logged (the next open removes what is left).
void removeFolders(const std::filesystem::path& dir, const FolderSet& folders);

/// A texture entry as readers resolve it: either slash, any letter case ("Diffuse/2_0_1.TIF" and
/// "diffuse\\2_0_1.tif" name the same file).
std::string normalisedEntry(std::string entry);

}  // namespace store
}  // namespace vsm::core
