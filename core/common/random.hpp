#pragma once

#include <cstdint>
#include <string>

namespace vsm::core {

/// 32 bits from the system's random source (std::random_device): for names and ids that must
/// differ between processes and runs (nonces, id prefixes), not for security. Thread-safe.
std::uint32_t randomWord();

/// randomWord() as 8 lowercase hex digits.
std::string randomHex();

}  // namespace vsm::core
