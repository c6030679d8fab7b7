#pragma once

// What a diff looks like: its map's colours, its legend and the PNG of GET
// /v1/models/{m}/diff.png and `vsm diff --png`.

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace vsm::core {

struct DisplacementMap;
struct RevisionDiff;

/// The diverging colour of a displacement: blue for -range, white for 0, red for +range (clamped),
/// transparent for NaN.
std::array<std::uint8_t, 4> divergingColour(double d, double range);

/// `map` coloured by divergingColour over [-range, range], RGBA 8 bits, row-major.
std::vector<std::uint8_t> colourMap(const DisplacementMap& map, double range);

/// What the colours of diff's map mean: "displacement from revision A to B along the surface
/// normal, metres: blue -R, white 0, red +R", R = diff.totals.maxAbs(), followed by the totals:
/// "; volume gained G m^3, lost L m^3, changed C m^2 (significant S m^2)".
std::string diffLegend(const RevisionDiff& diff);

/// diff's map as a PNG file coloured over [-R, R] (R = diff.totals.maxAbs()), a legend in its lower
/// left corner (the colour bar labelled "-R m", "0", "+R m", when the picture has room), the text
/// chunks
/// "Description" (diffLegend) and "vsm:range" (R in metres); a transparent `emptySize` square when
/// the diff has no map (nothing changed). Throws Error(Internal) when it cannot be encoded.
std::vector<std::byte> diffPng(const RevisionDiff& diff, int emptySize);

}  // namespace vsm::core
