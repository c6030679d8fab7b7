// Fuzz target: vsm's binary index of a hierarchy (decodeOpcIndex, core/opc/README.md "The
// index"). The index is only used when it names the hierarchy's stamp and its checksum holds, so
// raw mutations would stop there: the target takes the stamp from the input's own header and
// writes the input's checksum over its last 8 bytes, and the decoder's body parsing is what gets
// fuzzed. What decodes must encode and decode again to the same patches and record, and the head
// alone (decodeOpcIndexHead) to the same record and retired folders.
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <optional>
#include <span>
#include <vector>

#include "core/opc/opc_index.hpp"
#include "tests/fuzz/fuzz_support.hpp"

using namespace vsm;

namespace {

// The header: 8 bytes of magic, a 4-byte format, then inode, size and modification time.
constexpr std::size_t kStampAt = 8 + 4;
constexpr std::size_t kHeader = kStampAt + 24;

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < kHeader + 8) {
    return 0;
  }
  std::vector<std::byte> bytes(reinterpret_cast<const std::byte*>(data),
                               reinterpret_cast<const std::byte*>(data) + size);
  core::HierarchyStamp stamp;
  std::memcpy(&stamp.inode, bytes.data() + kStampAt, 8);
  std::memcpy(&stamp.size, bytes.data() + kStampAt + 8, 8);
  std::memcpy(&stamp.modifiedNs, bytes.data() + kStampAt + 16, 8);
  const std::uint64_t sum =
      core::opcIndexChecksum(std::span<const std::byte>(bytes).first(size - 8));
  std::memcpy(bytes.data() + size - 8, &sum, 8);

  // The head alone (what dropping a revision reads): its own checksum rarely holds after a
  // mutation, but its parsing must never fail otherwise.
  std::optional<core::IndexedRevision> head;
  fuzz::succeeds([&] { head = core::decodeOpcIndexHead(bytes, stamp); });
  // A delta (format 3) parses before its base is looked at: the input stands for both.
  fuzz::succeeds([&] { core::decodeOpcIndexDelta(bytes, stamp, bytes); });
  std::optional<core::OpcRevision> decoded;
  fuzz::succeeds([&] { decoded = core::decodeOpcIndex(bytes, stamp); });
  if (!decoded) {
    return 0;
  }
  std::vector<std::byte> again;
  fuzz::succeeds([&] {
    again =
        core::encodeOpcIndex(stamp, decoded->model, decoded->record ? &*decoded->record : nullptr,
                             head && head->retired ? &*head->retired : nullptr);
  });
  std::optional<core::IndexedRevision> headAgain;
  fuzz::succeeds([&] { headAgain = core::decodeOpcIndexHead(again, stamp); });
  fuzz::check(headAgain.has_value(), "a re-encoded index has a head that decodes alone");
  fuzz::check(headAgain->record.has_value() == decoded->record.has_value(),
              "the re-encoded head has the same record");
  fuzz::check(!head || headAgain->retired == head->retired,
              "the re-encoded head has the same retired folders");
  std::optional<core::OpcRevision> redecoded;
  fuzz::succeeds([&] { redecoded = core::decodeOpcIndex(again, stamp); });
  fuzz::check(redecoded.has_value(), "what decodes encodes to an index that decodes");
  fuzz::check(redecoded->model.patchCount() == decoded->model.patchCount(),
              "the re-encoded index has the same patches");
  fuzz::check(redecoded->record.has_value() == decoded->record.has_value(),
              "the re-encoded index has the same record");
  return 0;
}
