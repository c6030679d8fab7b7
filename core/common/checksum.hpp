#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

namespace vsm::core {

/// The checksum of vsm's binary files (the index, saved terrain footprints): 64 bits over 8-byte
/// little-endian words, the tail zero-padded, each word mixed by a multiply and an xor-shift. It
/// finds damage (torn writes, flipped bits), not tampering.
std::uint64_t checksum64(std::span<const std::byte> bytes);

}  // namespace vsm::core
