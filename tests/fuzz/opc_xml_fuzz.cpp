// Fuzz target: Patches/patchhierarchy.xml and Patch.xml parsing (readOpcModel, then validateOpc).
//
// Input: the hierarchy, then a line "%%", then a Patch.xml that every patch folder holds (without
// the line, the input is both), then optionally another line "%%" and the second hierarchy file
// of hidden levels, Patches/vsm-hidden-0123456789abcdef.xml (core/opc/README.md). The folders of a
// quadtree three levels deep (d_x_y, as vsm names them) exist, each with a real 9 x 9 V3f
// Positions.aara and V2f Coordinates.aara.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string>
#include <string_view>
#include <vector>

#include "core/opc/aara.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/validate.hpp"
#include "core/pyramid/patch_key.hpp"
#include "tests/fuzz/fuzz_support.hpp"

using namespace vsm;
namespace fs = std::filesystem;

namespace {

constexpr int kGrid = 9;

std::vector<std::byte> gridFile(core::AaraType type, int components) {
  core::AaraArray array;
  array.type = type;
  array.sizes = {kGrid, kGrid};
  std::vector<float> values;
  for (int y = 0; y < kGrid; ++y) {
    for (int x = 0; x < kGrid; ++x) {
      const float v[3] = {static_cast<float>(x), static_cast<float>(y), std::sin(x * 0.3f + y)};
      values.insert(values.end(), v, v + components);
    }
  }
  array.data.resize(values.size() * sizeof(float));
  std::memcpy(array.data.data(), values.data(), array.data.size());
  return core::encodeAara(array);
}

/// The OPC the inputs are written into; the Patch.xml of every folder links to one file.
struct Opc {
  fuzz::ScratchDir scratch{"opc-xml"};
  fs::path dir = scratch.path() / "opc";
  fs::path hierarchy = dir / "Patches" / "patchhierarchy.xml";
  fs::path patchXml = dir / "Patches" / "patch.xml.shared";
  fs::path hidden = dir / "Patches" / "vsm-hidden-0123456789abcdef.xml";

  Opc() {
    const std::vector<std::byte> positions = gridFile(core::AaraType::V3f, 3);
    const std::vector<std::byte> coordinates = gridFile(core::AaraType::V2f, 2);
    for (int depth = 0; depth <= 2; ++depth) {
      for (std::uint32_t y = 0; y < (1u << depth); ++y) {
        for (std::uint32_t x = 0; x < (1u << depth); ++x) {
          const fs::path folder = dir / "Patches" / core::PatchKey{depth, x, y}.toString();
          fs::create_directories(folder);
          fuzz::writeFile(folder / "Positions.aara", positions.data(), positions.size());
          fuzz::writeFile(folder / "Coordinates.aara", coordinates.data(), coordinates.size());
          fs::create_symlink("../patch.xml.shared", folder / "Patch.xml");
        }
      }
    }
  }
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const Opc opc;
  const std::string_view input(reinterpret_cast<const char*>(data), size);
  const std::size_t split = input.find("\n%%\n");
  const std::string_view hierarchy = input.substr(0, split);
  std::string_view patch = split == std::string_view::npos ? input : input.substr(split + 4);
  std::string_view hidden;
  if (const std::size_t second = patch.find("\n%%\n");
      split != std::string_view::npos && second != std::string_view::npos) {
    hidden = patch.substr(second + 4);
    patch = patch.substr(0, second);
  }
  fuzz::writeFile(opc.hierarchy, hierarchy.data(), hierarchy.size());
  fuzz::writeFile(opc.patchXml, patch.data(), patch.size());
  fuzz::writeFile(opc.hidden, hidden.data(), hidden.size());

  const bool read = fuzz::succeeds([&] {
    const core::Model model = core::readOpcModel(opc.dir);
    fuzz::check(model.patchCount() >= 1, "a model read has its root");
  });
  // Validation reads the same files and reports what is wrong as findings; a model that reads
  // may still have findings, one that does not read must have some.
  fuzz::succeeds([&] {
    const std::vector<core::Finding> findings = core::validateOpc(opc.dir);
    fuzz::check(read || !findings.empty(), "an unreadable OPC has findings");
  });
  return 0;
}
