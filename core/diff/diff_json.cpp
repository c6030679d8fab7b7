#include "core/diff/diff_json.hpp"

#include <cmath>
#include <cstddef>
#include <utility>

#include <nlohmann/json.hpp>

#include "core/diff/revision_diff.hpp"

namespace vsm::core {

namespace {

nlohmann::json number(double v) {
  return std::isfinite(v) ? nlohmann::json(v) : nlohmann::json(nullptr);
}

nlohmann::json boxJson(const Box3d& box) {
  if (box.empty()) {
    return nullptr;
  }
  return {{"min", {box.min.x, box.min.y, box.min.z}}, {"max", {box.max.x, box.max.y, box.max.z}}};
}

nlohmann::json statsJson(const DisplacementStats& s) {
  const bool any = s.samples > 0;
  return {{"samples", s.samples},
          {"skipped", s.skipped},
          {"area", s.area},
          {"changed_area", s.changedArea},
          {"noise", s.noise},
          {"min", any ? number(s.min) : nullptr},
          {"max", any ? number(s.max) : nullptr},
          {"mean", number(s.mean())},
          {"rms", number(s.rms())},
          {"max_abs", any ? number(s.maxAbs()) : nullptr},
          {"significant_area", s.significantArea},
          {"volume_gained", s.volumeGained},
          {"volume_lost", s.volumeLost},
          {"lod_mean", number(s.lodMean())},
          {"lod_max", any ? number(s.lodMax) : nullptr}};
}

}  // namespace

std::string diffJson(const RevisionDiff& diff, std::string_view model) {
  nlohmann::json patches = nlohmann::json::array();
  std::size_t removed = 0;
  for (const PatchDisplacement& p : diff.patches) {
    removed += p.removed ? 1 : 0;
    nlohmann::json entry = statsJson(p.stats);
    entry["key"] = p.key.toString();
    entry["box"] = boxJson(p.box);
    entry["removed"] = p.removed;
    entry["leaf"] = p.leaf;
    patches.push_back(std::move(entry));
  }
  nlohmann::json totals = statsJson(diff.totals);
  totals["shared_patches"] = diff.sharedPatches;
  totals["changed_patches"] = diff.patches.size() - removed;
  totals["removed_patches"] = removed;
  nlohmann::json body = {{"model", model},
                         {"from", diff.from},
                         {"to", diff.to},
                         {"epsilon", diff.epsilon},
                         {"registration_error", diff.registrationError},
                         {"totals", totals},
                         {"patches", std::move(patches)}};
  if (diff.map) {
    const TopDownGrid& g = diff.map->grid;
    body["map"] = {{"geographic", g.geographic},
                   {"width", g.width},
                   {"height", g.height},
                   {"x0", g.x0},
                   {"y0", g.y0},
                   {"dx", g.dx},
                   {"dy", g.dy}};
  }
  return body.dump();
}

}  // namespace vsm::core
