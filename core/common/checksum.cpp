#include "core/common/checksum.hpp"

#include <cstring>

namespace vsm::core {

std::uint64_t checksum64(std::span<const std::byte> bytes) {
  std::uint64_t h = 0x9e3779b97f4a7c15ULL ^ bytes.size();
  std::size_t i = 0;
  for (; i + 8 <= bytes.size(); i += 8) {
    std::uint64_t w;
    std::memcpy(&w, bytes.data() + i, 8);
    h = (h ^ w) * 0xff51afd7ed558ccdULL;
    h ^= h >> 29;
  }
  std::uint64_t w = 0;
  std::memcpy(&w, bytes.data() + i, bytes.size() - i);
  h = (h ^ w) * 0xc4ceb9fe1a85ec53ULL;
  return h ^ (h >> 32);
}

}  // namespace vsm::core
