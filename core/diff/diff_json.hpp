#pragma once

#include <string>
#include <string_view>

namespace vsm::core {

struct RevisionDiff;

/// The JSON body of GET /v1/models/{m}/diff and `vsm diff --json` (proto/openapi.yaml, Diff).
std::string diffJson(const RevisionDiff& diff, std::string_view model);

}  // namespace vsm::core
