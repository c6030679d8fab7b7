// Fuzz target: the daemon's configuration file (--config FILE: JSON with comments, nested or
// dotted keys, sizes and durations as strings), loaded, validated and described; what describe()
// prints must read back to the same configuration.
#include <cstddef>
#include <cstdint>

#include <nlohmann/json.hpp>

#include "server/config/config.hpp"
#include "tests/fuzz/fuzz_support.hpp"

using namespace vsm;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const fuzz::ScratchDir scratch("config");
  static const std::filesystem::path file = scratch.path() / "vsmd.json";
  fuzz::writeFile(file, data, size);

  server::Config config;
  if (!fuzz::succeeds([&] { server::loadConfigFile(file, config); })) {
    return 0;
  }
  if (!fuzz::succeeds([&] { config.validate(); })) {
    return 0;
  }
  const auto described = config.describe();
  server::Config copy;
  copy.token = config.token;  // described as "(redacted)"
  for (const auto& [key, value] : described) {
    // Empty paths are described as "(none)", the default.
    const bool none =
        (key == "port_file" || key == "viewer_dir" || key == "token_file") && value == "(none)";
    if (key != "token" && !none) {
      const bool set =
          fuzz::succeeds([&, &key = key, &value = value] { copy.set(key, nlohmann::json(value)); });
      fuzz::check(set, "describe() prints what set() reads");
    }
  }
  fuzz::check(copy.describe() == described, "a described configuration reads back the same");
  return 0;
}
