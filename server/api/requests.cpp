#include "server/api/requests.hpp"

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <initializer_list>
#include <numbers>
#include <string>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"

namespace vsm::server::api {

using core::Error;
using core::ErrorCode;
using nlohmann::json;

namespace {

/// The JSON object body of a write; rejects members other than `allowed` (typos fail loudly).
json objectBody(const http::Request& request, std::initializer_list<std::string_view> allowed) {
  json body = http::jsonBody(request);
  if (!body.is_object()) {
    throw Error(ErrorCode::InvalidArgument, "request body must be a JSON object");
  }
  for (const auto& [key, value] : body.items()) {
    if (std::find(allowed.begin(), allowed.end(), key) == allowed.end()) {
      throw Error(ErrorCode::InvalidArgument, "unknown member '" + key.substr(0, 64) + "'");
    }
  }
  return body;
}

std::string stringMember(const json& object, const char* name) {
  const auto it = object.find(name);
  if (it == object.end() || !it->is_string()) {
    throw Error(ErrorCode::InvalidArgument, std::string("'") + name + "' must be a string");
  }
  return it->get<std::string>();
}

double parseNumber(std::string_view text, std::string_view what) {
  double value = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  if (text.empty() || ec != std::errc() || end != text.data() + text.size() ||
      !std::isfinite(value)) {
    throw Error(ErrorCode::InvalidArgument, std::string(what) + " must be a finite number, not '" +
                                                std::string(text.substr(0, 32)) + "'");
  }
  return value;
}

/// `count` finite numbers separated by commas; throws naming `what` and the form `form`.
template <std::size_t N>
std::array<double, N> parseNumbers(std::string_view text, std::string_view what,
                                   std::string_view form) {
  std::array<double, N> v{};
  std::size_t count = 0;
  for (std::string_view rest = text;;) {
    const std::size_t comma = rest.find(',');
    if (count == N) {
      count = N + 1;
      break;
    }
    v[count++] = parseNumber(rest.substr(0, comma),
                             std::string("each ") + std::string(what) + " coordinate");
    if (comma == std::string_view::npos) {
      break;
    }
    rest.remove_prefix(comma + 1);
  }
  if (count != N) {
    throw Error(ErrorCode::InvalidArgument, std::string(what) + " must be " + std::to_string(N) +
                                                " numbers " + std::string(form));
  }
  return v;
}

/// Checks a ray's direction (`what` names it): not zero, and not so large that its length
/// overflows.
void checkDirection(const core::Vec3d& d, const std::string& what) {
  const double length = d.norm();
  if (!(length > 0) || !std::isfinite(length)) {
    throw Error(ErrorCode::InvalidArgument,
                what + " must not be zero (nor so large that its length overflows)");
  }
}

void checkMaxDistance(double value, const std::string& what) {
  if (!(value >= 0)) {
    throw Error(ErrorCode::InvalidArgument, what + " must be >= 0 (metres along the ray)");
  }
}

/// Member `name` of a ray object (`what` names the ray): an array of three finite numbers.
core::Vec3d vec3Member(const json& item, const char* name, const std::string& what) {
  const auto it = item.find(name);
  if (it == item.end()) {
    throw Error(ErrorCode::InvalidArgument, what + " has no '" + name + "'");
  }
  const json& v = *it;
  if (!v.is_array() || v.size() != 3 || !v[0].is_number() || !v[1].is_number() ||
      !v[2].is_number()) {
    throw Error(ErrorCode::InvalidArgument,
                what + ": '" + name + "' must be an array of three numbers [x, y, z]");
  }
  const core::Vec3d out{v[0].get<double>(), v[1].get<double>(), v[2].get<double>()};
  if (!out.finite()) {
    throw Error(ErrorCode::InvalidArgument, what + ": '" + name + "' must be finite");
  }
  return out;
}

}  // namespace

LodQuery parseLodQuery(std::string_view box, std::string_view resolution) {
  LodQuery out;
  const auto v = parseNumbers<6>(box, "box", "x0,y0,z0,x1,y1,z1");
  if (v[0] > v[3] || v[1] > v[4] || v[2] > v[5]) {
    throw Error(ErrorCode::InvalidArgument, "box must have x0 <= x1, y0 <= y1 and z0 <= z1");
  }
  out.box.min = {v[0], v[1], v[2]};
  out.box.max = {v[3], v[4], v[5]};
  out.resolution = parseNumber(resolution, "resolution");
  if (out.resolution <= 0) {
    throw Error(ErrorCode::InvalidArgument, "resolution must be greater than 0 (metres)");
  }
  return out;
}

CameraQuery parseCameraQuery(const http::Request& request) {
  const auto required = [&](std::string_view name) {
    auto value = request.queryParam(name);
    if (!value) {
      throw Error(ErrorCode::InvalidArgument,
                  "a camera lod needs eye=x,y,z&dir=x,y,z&up=x,y,z&fov=deg&height=px&sse=px "
                  "(width=px optional); '" +
                      std::string(name) + "' is missing");
    }
    return *value;
  };
  const auto vec = [&](std::string_view name) {
    const auto v = parseNumbers<3>(required(name), name, "x,y,z");
    return core::Vec3d{v[0], v[1], v[2]};
  };
  CameraQuery out;
  out.camera.eye = vec("eye");
  out.camera.dir = vec("dir");
  out.camera.up = vec("up");
  const double fovDegrees = parseNumber(required("fov"), "fov");
  out.camera.fovY = fovDegrees * std::numbers::pi / 180;
  out.camera.height = parseNumber(required("height"), "height");
  const auto width = request.queryParam("width");
  out.camera.width = width ? parseNumber(*width, "width") : out.camera.height;
  out.maxScreenError = parseNumber(required("sse"), "sse");
  if (!(out.maxScreenError > 0)) {
    throw Error(ErrorCode::InvalidArgument, "sse must be greater than 0 (pixels)");
  }
  core::checkCamera(out.camera);
  return out;
}

ModelRequest parseModelRequest(const http::Request& request) {
  const json body = objectBody(request, {"id", "source"});
  ModelRequest out;
  out.id = stringMember(body, "id");
  const auto source = body.find("source");
  if (source == body.end() || !source->is_object()) {
    throw Error(ErrorCode::InvalidArgument,
                R"('source' must be an object: {"path": ...} or {"import": ..., "patch_size": N})");
  }
  for (const auto& [key, value] : source->items()) {
    if (key != "path" && key != "import" && key != "patch_size" && key != "texture" &&
        key != "visible_texels_per_quad") {
      throw Error(ErrorCode::InvalidArgument, "unknown member 'source." + key.substr(0, 64) + "'");
    }
  }
  const bool byPath = source->contains("path");
  if (byPath == source->contains("import")) {
    throw Error(ErrorCode::InvalidArgument, "'source' needs exactly one of 'path' and 'import'");
  }
  if (byPath) {
    if (source->contains("patch_size") || source->contains("texture") ||
        source->contains("visible_texels_per_quad")) {
      throw Error(ErrorCode::InvalidArgument,
                  "'patch_size', 'texture' and 'visible_texels_per_quad' go with 'import' only");
    }
    out.path = stringMember(*source, "path");
    return out;
  }
  if (const auto size = source->find("patch_size"); size != source->end()) {
    if (!size->is_number_integer()) {
      throw Error(ErrorCode::InvalidArgument, "'patch_size' must be an integer (2^n + 1)");
    }
    const auto value = size->get<std::int64_t>();
    out.patchSize = value < 0 || value > 1'000'000 ? -1 : static_cast<int>(value);
  }
  if (const auto k = source->find("visible_texels_per_quad"); k != source->end()) {
    if (!k->is_number_integer()) {
      throw Error(ErrorCode::InvalidArgument,
                  "'visible_texels_per_quad' must be an integer (a power of two)");
    }
    const auto value = k->get<std::int64_t>();
    out.visibleTexelsPerQuad = value < 0 || value > 1'000'000 ? -1 : static_cast<int>(value);
  }
  if (const auto texture = source->find("texture"); texture != source->end()) {
    if (!texture->is_string() || (*texture != "relief" && *texture != "none")) {
      throw Error(ErrorCode::InvalidArgument, R"('texture' must be "relief" or "none")");
    }
    out.untextured = *texture == "none";
  }
  out.import = stringMember(*source, "import");
  return out;
}

MergeRequest parseMergeRequest(const http::Request& request) {
  const json body = objectBody(request, {"type", "target", "source", "register"});
  const auto type = body.find("type");
  if (type == body.end() || !type->is_string() || *type != "merge") {
    throw Error(ErrorCode::InvalidArgument,
                R"('type' must be "merge" (imports are submitted with POST /v1/models))");
  }
  const auto target = body.find("target");
  const auto source = body.find("source");
  if (target == body.end() || !target->is_string() || source == body.end() ||
      !source->is_string()) {
    throw Error(ErrorCode::InvalidArgument, "'target' and 'source' must be model ids (strings)");
  }
  MergeRequest out;
  out.target = target->get<std::string>();
  out.source = source->get<std::string>();
  if (const auto reg = body.find("register"); reg != body.end()) {
    if (!reg->is_boolean()) {
      throw Error(ErrorCode::InvalidArgument, "'register' must be true or false");
    }
    out.registerFirst = reg->get<bool>();
  }
  return out;
}

std::vector<core::Ray> parseRayQuery(const http::Request& request, std::size_t maxRays) {
  std::vector<core::Ray> rays;
  if (request.method == http::Method::Post) {
    const json body = objectBody(request, {"rays"});
    const auto list = body.find("rays");
    if (list == body.end() || !list->is_array() || list->empty()) {
      throw Error(ErrorCode::InvalidArgument,
                  R"('rays' must be a non-empty array of {"origin": [x, y, z], "direction": )"
                  R"([dx, dy, dz], "max_distance": D})");
    }
    if (list->size() > maxRays) {
      throw Error(ErrorCode::InvalidArgument,
                  std::to_string(list->size()) + " rays, more than the " + std::to_string(maxRays) +
                      " of one request; split the request");
    }
    for (std::size_t i = 0; i < list->size(); ++i) {
      const std::string what = "ray " + std::to_string(i + 1);
      const json& item = (*list)[i];
      if (!item.is_object()) {
        throw Error(ErrorCode::InvalidArgument,
                    what + R"( must be an object {"origin", "direction", "max_distance"})");
      }
      for (const auto& [key, value] : item.items()) {
        if (key != "origin" && key != "direction" && key != "max_distance") {
          throw Error(ErrorCode::InvalidArgument,
                      what + ": unknown member '" + key.substr(0, 64) + "'");
        }
      }
      core::Ray ray;
      ray.origin = vec3Member(item, "origin", what);
      ray.direction = vec3Member(item, "direction", what);
      checkDirection(ray.direction, what + ": 'direction'");
      if (const auto max = item.find("max_distance"); max != item.end()) {
        if (!max->is_number() || !std::isfinite(max->get<double>())) {
          throw Error(ErrorCode::InvalidArgument, what + ": 'max_distance' must be a number");
        }
        ray.maxDistance = max->get<double>();
        checkMaxDistance(ray.maxDistance, what + ": 'max_distance'");
      }
      rays.push_back(ray);
    }
    return rays;
  }
  const auto origin = request.queryParam("origin");
  const auto direction = request.queryParam("direction");
  if (!origin || !direction) {
    throw Error(ErrorCode::InvalidArgument,
                "a ray needs origin=x,y,z&direction=dx,dy,dz (max_distance=D optional), or a "
                R"(POST of {"rays": [...]}; ')" +
                    std::string(origin ? "direction" : "origin") + "' is missing");
  }
  const auto o = parseNumbers<3>(*origin, "origin", "x,y,z");
  const auto d = parseNumbers<3>(*direction, "direction", "dx,dy,dz");
  core::Ray ray;
  ray.origin = {o[0], o[1], o[2]};
  ray.direction = {d[0], d[1], d[2]};
  checkDirection(ray.direction, "direction");
  if (const auto max = request.queryParam("max_distance")) {
    ray.maxDistance = parseNumber(*max, "max_distance");
    checkMaxDistance(ray.maxDistance, "max_distance");
  }
  rays.push_back(ray);
  return rays;
}

}  // namespace vsm::server::api
