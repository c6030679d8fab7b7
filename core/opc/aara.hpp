#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

namespace vsm::core {

/// Element types of Aardvark array files (`.aara`), see OPC.md.
enum class AaraType { Byte, Int, Float, Double, V2f, V3f, V2d, V3d, C3b, C4b, C3f, C4f };

std::string_view toString(AaraType type);
/// Exact, case-sensitive type names as OPC.md lists them; nullopt for anything else.
std::optional<AaraType> parseAaraType(std::string_view name);
std::size_t elementSize(AaraType type);

/// A decoded array: type, sizes (Size[0] = columns, fastest) and the packed little-endian elements.
struct AaraArray {
  AaraType type = AaraType::Byte;
  std::vector<std::int32_t> sizes;
  std::vector<std::byte> data;

  std::size_t elementCount() const;
};

/// Decodes `.aara` bytes. Throws Error(Corrupt) naming `what` (e.g. the file path) on a bad type
/// name, a dimension count outside 1..4, a negative size, truncation or trailing bytes.
AaraArray decodeAara(std::span<const std::byte> bytes, std::string_view what);
std::vector<std::byte> encodeAara(const AaraArray& array);
/// The header alone (type name, dimension count, sizes), for writers that append the elements
/// themselves. Throws Error(InvalidArgument) for 0 or more than 4 sizes or negative ones.
std::vector<std::byte> encodeAaraHeader(AaraType type, std::span<const std::int32_t> sizes);

/// Reads and decodes a file. Throws Error(NotFound / Io / Corrupt).
AaraArray readAaraFile(const std::filesystem::path& path);

}  // namespace vsm::core
