// Fuzz target: `.aara` decoding, in memory (decodeAara) and from a file (readAaraFile, which
// checks the header against the file's length before it allocates the data).
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "core/opc/aara.hpp"
#include "tests/fuzz/fuzz_support.hpp"

using namespace vsm;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const fuzz::ScratchDir scratch("aara");
  static const std::filesystem::path file = scratch.path() / "Positions.aara";
  const std::span<const std::byte> bytes(reinterpret_cast<const std::byte*>(data), size);

  std::optional<core::AaraArray> decoded;
  fuzz::succeeds([&] { decoded = core::decodeAara(bytes, "input"); });
  fuzz::writeFile(file, data, size);
  std::optional<core::AaraArray> read;
  fuzz::succeeds([&] { read = core::readAaraFile(file); });

  // The file reader and the decoder agree, and what decodes encodes back to the same bytes.
  fuzz::check(decoded.has_value() == read.has_value(), "readAaraFile agrees with decodeAara");
  if (decoded) {
    fuzz::check(
        decoded->type == read->type && decoded->sizes == read->sizes && decoded->data == read->data,
        "readAaraFile reads what decodeAara decodes");
    fuzz::check(decoded->data.size() == decoded->elementCount() * core::elementSize(decoded->type),
                "the data is count x element size");
    const std::vector<std::byte> encoded = core::encodeAara(*decoded);
    fuzz::check(std::equal(encoded.begin(), encoded.end(), bytes.begin(), bytes.end()),
                "encodeAara(decodeAara(bytes)) == bytes");
  }
  return 0;
}
