#pragma once

#include <compare>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>

namespace vsm::core {

/// The four children of a patch. NW is the upper-left quarter (lower x, lower y: grid row 0 is the
/// top), matching OPC's nw/ne/sw/se.
enum class Quadrant : std::uint8_t { NW = 0, NE = 1, SW = 2, SE = 3 };

inline constexpr Quadrant kQuadrants[] = {Quadrant::NW, Quadrant::NE, Quadrant::SW, Quadrant::SE};

/// OPC's name of a quadrant: "nw", "ne", "sw", "se".
std::string_view toString(Quadrant q);
std::optional<Quadrant> parseQuadrant(std::string_view name);

/// Position of a patch in the quadtree: depth below the root and column/row among the 2^depth x
/// 2^depth patches of that depth. The root is (0, 0, 0). Because depth counts from the root, keys
/// stay valid when a merge adds levels at the bottom.
struct PatchKey {
  static constexpr int kMaxDepth = 30;

  int depth = 0;
  std::uint32_t x = 0;
  std::uint32_t y = 0;

  static PatchKey root() { return {}; }
  bool isRoot() const { return depth == 0; }
  /// The parent; nullopt for the root.
  std::optional<PatchKey> parent() const;
  /// Which quarter of its parent this key is; precondition: !isRoot().
  Quadrant quadrant() const;
  /// Precondition: depth < kMaxDepth.
  PatchKey child(Quadrant q) const;
  /// True when `other` is this key or lies below it.
  bool isAncestorOrSelfOf(const PatchKey& other) const;

  /// "depth_x_y", e.g. "3_5_2"; also the folder name vsm writes.
  std::string toString() const;
  /// Room for any key's toString().
  static constexpr std::size_t kMaxText = 40;
  /// toString() written into `out`, without allocating (a digest of 10^6 patches' folders).
  std::string_view toChars(char (&out)[kMaxText]) const;
  /// Inverse of toString(); nullopt on anything else (including out-of-range x or y).
  static std::optional<PatchKey> parse(std::string_view text);

  friend bool operator==(const PatchKey&, const PatchKey&) = default;
  /// Orders by depth, then row, then column: parents before children, rows in reading order.
  friend std::strong_ordering operator<=>(const PatchKey& a, const PatchKey& b) {
    if (auto c = a.depth <=> b.depth; c != 0)
      return c;
    if (auto c = a.y <=> b.y; c != 0)
      return c;
    return a.x <=> b.x;
  }
};

struct PatchKeyHash {
  std::size_t operator()(const PatchKey& k) const noexcept {
    return std::hash<std::uint64_t>{}((std::uint64_t{k.x} << 32 | k.y) * 31 + k.depth);
  }
};

}  // namespace vsm::core
