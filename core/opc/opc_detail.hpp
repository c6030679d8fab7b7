#pragma once

// Internal to core/opc: shared by aara.cpp, opc_files.cpp, opc_reader.cpp, opc_writer.cpp,
// stored_file.cpp, texture_file.cpp and validate.cpp. Not part of the module's interface; other
// modules include aara.hpp, opc_reader.hpp, opc_writer.hpp and validate.hpp only.

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <limits>
#include <map>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "core/opc/aara.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core::detail {

/// The header of an `.aara` file: what decodeAara checks before it looks at the data.
struct AaraHeader {
  AaraType type = AaraType::Byte;
  std::vector<std::int32_t> sizes;
  std::size_t headerBytes = 0;
  /// count x element size: the exact number of bytes that must follow the header.
  std::size_t dataBytes = 0;
};

/// Decodes and checks the header at the start of `bytes` (which may hold more than the header).
/// Throws Error(Corrupt) naming `what` like decodeAara.
AaraHeader decodeAaraHeader(std::span<const std::byte> bytes, std::string_view what);
/// Reads only the header of an `.aara` file. Throws Error(NotFound / Io / Corrupt).
AaraHeader readAaraHeader(const std::filesystem::path& path);

/// Opens a file read-only (close-on-exec). Throws Error(NotFound) when it does not exist,
/// Error(Unavailable) when the process is out of descriptors, Error(Io) otherwise.
int openForReading(const std::filesystem::path& path);

/// Reads up to out.size() bytes of the open file `fd` at `offset` (fewer only at its end; retried
/// on EINTR); returns how many. Throws Error(Io) naming `what` when a read fails.
std::size_t readAt(int fd, std::size_t offset, std::span<std::byte> out, std::string_view what);

/// Reads a whole file, or its first `maxBytes`. Throws Error(NotFound) when it does not exist,
/// Error(Io) on any other failure.
std::vector<std::byte> readFile(const std::filesystem::path& path,
                                std::size_t maxBytes = std::numeric_limits<std::size_t>::max());

/// ASCII case-insensitive equality (file and element names).
bool equalsIgnoreCase(std::string_view a, std::string_view b);

/// The entry of `dir` called `name` in any letter case; the exact spelling wins when several
/// match. nullopt when there is none (or `dir` cannot be listed).
std::optional<std::filesystem::path> findEntry(const std::filesystem::path& dir,
                                               std::string_view name);
/// findEntry's entry, or `dir`/`name` as spelled when there is none (to open and report missing).
std::filesystem::path entryPath(const std::filesystem::path& dir, std::string_view name);

/// True for a name that stays inside its directory: not empty, not ".", no "..", "/" or "\".
bool isSafeName(std::string_view name);

/// True for a texture path relative to Images/ (segments separated by "\\" or "/") whose every
/// segment is a safe name.
bool isSafeTexturePath(std::string_view path);

/// The texture file a Patch.xml entry names: Images/ (any letter case) joined with the entry's
/// segments, each resolved case-insensitively, trying the extensions readers try (.dds, .tif,
/// .tiff) when the named file does not exist. nullopt when nothing matches.
std::optional<std::filesystem::path> findTextureFile(const std::filesystem::path& dir,
                                                     std::string_view entry);

/// What readOpc learnt about one patch beyond its PatchInfo (for validateOpc).
struct PatchDetails {
  std::filesystem::path xmlFile;
  /// Standard elements other readers require that the Patch.xml lacks.
  std::vector<std::string> missingElements;
  std::string geometryType;
  bool hasExtension = false;
  std::optional<std::string> extensionKey;
  std::optional<double> extensionResolution;
  /// Boxes were missing from the XML and computed from the data.
  bool boxesFromData = false;
};

/// Everything readOpc reads: the model plus what validation needs to know about the files.
struct OpcContents {
  Model model;
  std::filesystem::path patchesDir;
  std::filesystem::path hierarchyFile;
  /// The second hierarchy file, naming the hidden levels (core/opc/README.md), when there is one.
  std::optional<std::filesystem::path> hiddenFile;
  std::vector<double> avgGeometrySizes;
  bool hasHierarchyExtension = false;
  /// The hierarchy's <Vsm><Revision> record, when it has one.
  std::optional<RevisionRecord> revision;
  std::map<PatchKey, PatchDetails> patches;
  /// SubPatchMap keys no walk from the root reaches.
  std::vector<std::string> unreachableItems;
  /// Other readers' caches (`hierarchy.cache`) found beside the hierarchy.
  std::vector<std::filesystem::path> hierarchyCaches;
};

/// The reader behind readOpcModel, of the hierarchy file `hierarchyName` under Patches/ and the
/// second file it names (hidden levels) unless `withHidden` is false (what other OPC readers see);
/// throws as readOpcModel does.
OpcContents readOpc(const std::filesystem::path& dir,
                    std::string_view hierarchyName = "patchhierarchy.xml", bool withHidden = true);

/// Float32 rounding of one stored coordinate of `grid`, in global units: half an ulp of its
/// largest local coordinate (2^-24 x maxAbsLocal), scaled by the linear part of Local2Global.
double roundingOf(const PatchGrid& grid);
/// Largest absolute row sum of the linear part: how much a local error can grow globally.
double linearScale(const Mat4d& m);

}  // namespace vsm::core::detail
