#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include "core/common/progress.hpp"

namespace vsm::core {

/// One finding of validateOpc: where (a file or patch) and what is wrong.
struct Finding {
  std::string where;
  std::string message;
};

/// Checks every invariant of the model and the format: the hierarchy is a tree whose folders
/// exist; each .aara decodes with the right type and size; stored boxes contain exactly the
/// vertices (within float32 rounding); parents' boxes contain their children's; every defined
/// parent vertex equals the child vertex it was reduced from (within the float32 rounding of both
/// patches' stored coordinates); resolutions match; AvgGeometrySizes has enough entries and
/// realistic values; no stale hierarchy.cache. Returns all findings; empty when valid.
std::vector<Finding> validateOpc(const std::filesystem::path& dir, Progress* progress = nullptr);

}  // namespace vsm::core
