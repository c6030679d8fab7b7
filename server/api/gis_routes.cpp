#include "server/api/gis_routes.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/common/numbers.hpp"
#include "core/io/geoid.hpp"
#include "core/io/geotiff.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "core/tiles/heights.hpp"
#include "core/tiles/quantized_mesh.hpp"
#include "server/api/etags.hpp"
#include "server/api/route_helpers.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"
#include "server/models/patch_data.hpp"

namespace vsm::server::api {

using core::Error;
using core::ErrorCode;
using core::GeoPoint;
using nlohmann::json;

namespace {

/// Points per elevation request (locations, or samples along them): Open Topo Data's public API
/// allows 100; one core samples about this many in well under a second.
constexpr std::size_t kMaxPoints = 1000;
/// Samples per profile.
constexpr std::size_t kMaxProfileSamples = 10000;
/// Pixels per coverage request (64 MiB of float32).
constexpr std::size_t kMaxCoveragePixels = std::size_t{4096} * 4096;

constexpr std::string_view kCrs84 = "http://www.opengis.net/def/crs/OGC/1.3/CRS84";
constexpr std::string_view kGeoTiff = "image/tiff; application=geotiff";
constexpr std::string_view kHeightReference =
    "metres above the WGS 84 ellipsoid (no geoid model is applied)";

/// The geoid `?height=orthometric` asks for (the installed grid), or null for `?height=ellipsoid`
/// and no `?height=`. Throws Error(InvalidArgument) for another value, or for orthometric
/// heights when no geoid grid is installed.
std::shared_ptr<const core::GeoidGrid> requestedGeoid(const http::Request& request) {
  const auto height = request.queryParam("height");
  if (!height || *height == "ellipsoid") {
    return nullptr;
  }
  if (*height != "orthometric") {
    throw Error(ErrorCode::InvalidArgument,
                "height must be 'ellipsoid' or 'orthometric', not '" + height->substr(0, 40) + "'");
  }
  auto geoid = core::GeoidGrid::installed();
  if (geoid == nullptr) {
    throw Error(ErrorCode::InvalidArgument,
                "orthometric heights need a geoid grid, and none is installed (Debian: apt-get "
                "install proj-data, or set VSM_GEOID_GRID)");
  }
  return geoid;
}

/// What the answer says its heights are measured from.
std::string heightReference(const core::GeoidGrid* geoid) {
  return geoid == nullptr ? std::string(kHeightReference)
                          : "metres above the EGM96 geoid (orthometric: the heights above the WGS "
                            "84 ellipsoid less the undulation of " +
                                geoid->name() + ")";
}

/// What a height query answers from: the model as served, the snapshot ?rev= / ?v= name, and its
/// terrain layer (footprints).
struct HeightModel {
  std::string id;
  models::ModelRegistry::Served served;
  std::shared_ptr<const core::ModelSnapshot> snapshot;
  std::shared_ptr<const core::TerrainLayer> layer;
};

HeightModel heightModel(models::ModelRegistry& models, models::PatchData& data,
                        const std::string& id, const http::Request& request) {
  HeightModel m{id, models.getServed(id), nullptr, nullptr};
  m.snapshot = versionedSnapshot(*m.served.live, request);
  if (m.snapshot->model->empty()) {
    throw Error(ErrorCode::NotFound, "model '" + id + "' has no patches");
  }
  m.layer = data.terrainLayer(m.served, m.snapshot, models::Asker::Pool);
  if (!m.layer->heightField) {
    throw Error(ErrorCode::NotFound, "model '" + id + "' has no heights: " + m.layer->reason);
  }
  return m;
}

double number(std::string_view text, std::string_view what) {
  const auto value = core::parseDouble(std::string(http::trim(text)));
  if (!value || !std::isfinite(*value)) {
    throw Error(ErrorCode::InvalidArgument, std::string(what) + " must be a number, not '" +
                                                std::string(text.substr(0, 40)) + "'");
  }
  return *value;
}

GeoPoint checkedPoint(double lat, double lon, std::size_t index) {
  if (lat < -90 || lat > 90 || lon < -180 || lon > 180) {
    throw Error(ErrorCode::InvalidArgument,
                "location " + std::to_string(index + 1) + " (" + std::to_string(lat) + ", " +
                    std::to_string(lon) +
                    ") is outside the world: latitude must be in -90..90 and longitude in "
                    "-180..180 (Open Topo Data's order is lat,lon)");
  }
  return {lon, lat};
}

/// "lat,lon|lat,lon|..." (Open Topo Data's `locations`).
std::vector<GeoPoint> parseLocations(std::string_view text, std::string_view what,
                                     std::size_t max) {
  std::vector<GeoPoint> points;
  if (http::trim(text).empty()) {
    throw Error(ErrorCode::InvalidArgument, std::string(what) + " is empty");
  }
  if (static_cast<std::size_t>(std::count(text.begin(), text.end(), '|')) >= max) {
    throw Error(ErrorCode::InvalidArgument, std::string(what) + " has more than " +
                                                std::to_string(max) + " points; split the request");
  }
  std::size_t start = 0;
  while (start <= text.size()) {
    const std::size_t bar = std::min(text.find('|', start), text.size());
    const std::string_view pair = text.substr(start, bar - start);
    const std::size_t comma = pair.find(',');
    if (comma == std::string_view::npos) {
      throw Error(ErrorCode::InvalidArgument, std::string(what) +
                                                  " takes lat,lon pairs separated by '|', not '" +
                                                  std::string(pair.substr(0, 40)) + "'");
    }
    points.push_back(checkedPoint(number(pair.substr(0, comma), "a latitude"),
                                  number(pair.substr(comma + 1), "a longitude"), points.size()));
    start = bar + 1;
  }
  return points;
}

std::optional<std::size_t> parseSamples(const std::optional<std::string>& text, std::size_t max) {
  if (!text) {
    return std::nullopt;
  }
  const double n = number(*text, "samples");
  if (n < 2 || n > static_cast<double>(max) || n != std::floor(n)) {
    throw Error(ErrorCode::InvalidArgument,
                "samples must be an integer from 2 to " + std::to_string(max));
  }
  return static_cast<std::size_t>(n);
}

/// The points of a POST body: a GeoJSON Point, MultiPoint or LineString (or a Feature of one),
/// coordinates [lon, lat]; or Open Topo Data's JSON form {"locations": "lat,lon|..." or
/// [[lat, lon], ...] or [{"lat": .., "lng": ..}, ...], "samples": N}.
std::vector<GeoPoint> bodyPoints(const std::string& body, std::optional<std::size_t>& samples) {
  const json doc = json::parse(body, nullptr, false);
  if (doc.is_discarded() || !doc.is_object()) {
    throw Error(ErrorCode::InvalidArgument,
                "the body must be JSON: a GeoJSON Point, MultiPoint or LineString, or "
                "{\"locations\": \"lat,lon|...\"}");
  }
  const json& geometry =
      doc.value("type", "") == "Feature" && doc.contains("geometry") ? doc.at("geometry") : doc;
  std::vector<GeoPoint> points;
  const auto add = [&](const json& pair, bool lonFirst) {
    if (points.size() >= kMaxPoints) {
      throw Error(ErrorCode::InvalidArgument,
                  "more than " + std::to_string(kMaxPoints) + " points; split the request");
    }
    if (!pair.is_array() || pair.size() < 2 || !pair[0].is_number() || !pair[1].is_number()) {
      throw Error(ErrorCode::InvalidArgument, "a position must be an array of two numbers");
    }
    const double a = pair[0].get<double>(), b = pair[1].get<double>();
    points.push_back(lonFirst ? checkedPoint(b, a, points.size())
                              : checkedPoint(a, b, points.size()));
  };
  if (doc.contains("samples")) {
    samples = parseSamples(doc.at("samples").is_string() ? doc.at("samples").get<std::string>()
                                                         : doc.at("samples").dump(),
                           kMaxPoints);
  }
  const std::string type = geometry.is_object() ? geometry.value("type", "") : "";
  if (type == "Point" || type == "MultiPoint" || type == "LineString") {
    const json& coordinates = geometry.value("coordinates", json());
    if (type == "Point") {
      add(coordinates, true);
    } else if (coordinates.is_array()) {
      for (const json& pair : coordinates) {
        add(pair, true);
      }
    }
  } else if (doc.contains("locations")) {
    const json& locations = doc.at("locations");
    if (locations.is_string()) {
      points = parseLocations(locations.get<std::string>(), "locations", kMaxPoints);
    } else if (locations.is_array()) {
      for (const json& item : locations) {
        if (item.is_object()) {
          add(json::array(
                  {item.value("lat", json()), item.value("lng", item.value("lon", json()))}),
              false);
        } else {
          add(item, false);
        }
      }
    }
  } else if (!type.empty()) {
    throw Error(ErrorCode::InvalidArgument, "GeoJSON " + type +
                                                " is not taken: send a Point, MultiPoint or "
                                                "LineString");
  }
  if (points.empty()) {
    throw Error(ErrorCode::InvalidArgument, "the body names no points");
  }
  return points;
}

json locationJson(const GeoPoint& p) {
  return {{"lat", p.lat}, {"lng", p.lon}};
}

/// A result; its elevation above the ellipsoid, or above the geoid when `geoid` is given.
json sampleJson(const std::string& id, const GeoPoint& p, const core::HeightSample& s,
                const core::GeoidGrid* geoid) {
  const double h = geoid == nullptr ? s.height : s.height - geoid->undulation(p.lon, p.lat);
  json out = {{"dataset", id},
              {"elevation", std::isnan(h) ? json(nullptr) : json(h)},
              {"location", locationJson(p)}};
  if (s.depth >= 0) {
    out["depth"] = s.depth;
    out["resolution"] = s.resolution;
  } else {
    out["depth"] = nullptr;
    out["resolution"] = nullptr;
  }
  return out;
}

http::Response heightsAnswer(const HeightModel& m, json results, const core::GeoidGrid* geoid,
                             json extra = json::object()) {
  json body = {{"status", "OK"},
               {"results", std::move(results)},
               {"model", m.id},
               {"model_version", m.snapshot->version},
               {"height_reference", heightReference(geoid)}};
  body.update(extra);
  http::Response response = http::jsonResponse(200, body);
  response.set("X-VSM-Model-Version", std::to_string(m.snapshot->version));
  return withCache(std::move(response), http::cache_control::kRevalidate);
}

/// GET or POST /v1/models/{m}/elevation.
http::Response getElevation(models::ModelRegistry& models, models::PatchData& data,
                            const http::Request& request) {
  const auto geoid = requestedGeoid(request);
  std::optional<std::size_t> samples = parseSamples(request.queryParam("samples"), kMaxPoints);
  std::vector<GeoPoint> points;
  if (const auto locations = request.queryParam("locations")) {
    points = parseLocations(*locations, "locations", kMaxPoints);
  } else if (request.method == http::Method::Post && !request.body.empty()) {
    points = bodyPoints(request.body, samples);
  } else {
    throw Error(ErrorCode::InvalidArgument,
                "elevation needs ?locations=lat,lon|lat,lon... (or a JSON body with POST)");
  }
  if (samples) {
    std::vector<GeoPoint> along;
    for (const core::PathSample& s : core::samplePath(points, *samples)) {
      along.push_back(s.point);
    }
    points = std::move(along);
  }
  const HeightModel m = heightModel(models, data, request.param("m"), request);
  const auto heights = core::sampleHeights(*m.snapshot->model, *m.layer, points,
                                           data.gridLoader(m.served, *m.snapshot));
  json results = json::array();
  for (std::size_t i = 0; i < points.size(); ++i) {
    results.push_back(sampleJson(m.id, points[i], heights[i], geoid.get()));
  }
  return heightsAnswer(m, std::move(results), geoid.get());
}

/// GET /v1/models/{m}/profile?line=lat,lon|...&samples=N.
http::Response getProfile(models::ModelRegistry& models, models::PatchData& data,
                          const http::Request& request) {
  const auto geoid = requestedGeoid(request);
  const auto line = request.queryParam("line");
  if (!line) {
    throw Error(ErrorCode::InvalidArgument, "profile needs ?line=lat,lon|lat,lon...");
  }
  const std::vector<GeoPoint> vertices = parseLocations(*line, "line", kMaxPoints);
  if (vertices.size() < 2) {
    throw Error(ErrorCode::InvalidArgument, "a line needs at least two points");
  }
  std::optional<std::size_t> samples =
      parseSamples(request.queryParam("samples"), kMaxProfileSamples);
  const HeightModel m = heightModel(models, data, request.param("m"), request);
  const auto load = data.gridLoader(m.served, *m.snapshot);
  double length = 0;
  core::GeoRect box;
  for (std::size_t i = 0; i < vertices.size(); ++i) {
    box.extend(vertices[i].lon, vertices[i].lat);
    if (i > 0) {
      length += core::greatCircleDistance(vertices[i - 1], vertices[i]);
    }
  }
  const double finest = core::finestResolution(*m.snapshot->model, *m.layer, box);
  if (!samples) {
    // One sample per finest cell along the line (the leaves' resolution), within the bound.
    const double wanted = finest > 0 ? std::ceil(length / finest) + 1 : 2;
    samples =
        static_cast<std::size_t>(std::clamp(wanted, 2.0, static_cast<double>(kMaxProfileSamples)));
  }
  const std::vector<core::PathSample> path = core::samplePath(vertices, *samples);
  std::vector<GeoPoint> points;
  for (const core::PathSample& s : path) {
    points.push_back(s.point);
  }
  const auto heights = core::sampleHeights(*m.snapshot->model, *m.layer, points, load);
  json results = json::array();
  for (std::size_t i = 0; i < path.size(); ++i) {
    json r = sampleJson(m.id, points[i], heights[i], geoid.get());
    r["distance"] = path[i].distance;
    results.push_back(std::move(r));
  }
  return heightsAnswer(m, std::move(results), geoid.get(),
                       {{"length", length},
                        {"samples", path.size()},
                        {"finest_resolution", finest > 0 ? json(finest) : json(nullptr)}});
}

// ---- coverages
// -----------------------------------------------------------------------------------

void checkCrs(const std::optional<std::string>& crs) {
  if (!crs) {
    return;
  }
  for (const std::string_view known :
       {std::string_view("EPSG:4326"), std::string_view("OGC:CRS84"), kCrs84,
        std::string_view("http://www.opengis.net/def/crs/EPSG/0/4326"),
        std::string_view("[EPSG:4326]"), std::string_view("[OGC:CRS84]")}) {
    if (http::equalsIgnoreCase(*crs, known)) {
      return;
    }
  }
  throw Error(ErrorCode::InvalidArgument,
              "unknown or unsupported CRS '" + crs->substr(0, 80) +
                  "': coverages are served in longitude/latitude on WGS 84 (EPSG:4326, "
                  "OGC:CRS84); reproject with gdalwarp");
}

/// The pixel grid of the whole model: pixel centres on the finest leaf's vertices.
core::TopDownGrid wholeGrid(const HeightModel& m, models::PatchData& data) {
  const core::GeoRect& b = m.layer->bounds;
  double spacing = core::finestSpacingDegrees(*m.snapshot->model, *m.layer, b,
                                              data.gridLoader(m.served, *m.snapshot));
  if (!(spacing > 0)) {
    spacing = std::max(b.east - b.west, b.north - b.south) / 256;
  }
  // Within GDAL's and our pixel bound: coarser when the model is larger.
  while (((b.east - b.west) / spacing + 1) * ((b.north - b.south) / spacing + 1) >
         static_cast<double>(std::size_t{1} << 40)) {
    spacing *= 2;
  }
  core::TopDownGrid g;
  g.geographic = true;
  g.dx = g.dy = spacing;
  g.x0 = b.west - spacing / 2;
  g.y0 = b.north + spacing / 2;
  g.width = static_cast<int>(std::max(1.0, std::round((b.east - b.west) / spacing + 1)));
  g.height = static_cast<int>(std::max(1.0, std::round((b.north - b.south) / spacing + 1)));
  return g;
}

/// "Lon(a:b),Lat(c:d)" or "Lon(w),Lat(h)": the value of each axis named.
struct AxisValues {
  std::optional<std::string> lon, lat;
};
AxisValues parseAxes(std::string_view text, std::string_view what) {
  AxisValues out;
  std::size_t start = 0;
  while (start < text.size()) {
    const std::size_t open = text.find('(', start);
    const std::size_t close = open == std::string_view::npos ? open : text.find(')', open);
    if (close == std::string_view::npos) {
      throw Error(ErrorCode::InvalidArgument, std::string(what) +
                                                  " takes Lon(...),Lat(...), not '" +
                                                  std::string(text.substr(0, 80)) + "'");
    }
    const std::string_view axis = http::trim(text.substr(start, open - start));
    const std::string value(text.substr(open + 1, close - open - 1));
    if (http::equalsIgnoreCase(axis, "Lon") || http::equalsIgnoreCase(axis, "Long") ||
        http::equalsIgnoreCase(axis, "x") || http::equalsIgnoreCase(axis, "E")) {
      out.lon = value;
    } else if (http::equalsIgnoreCase(axis, "Lat") || http::equalsIgnoreCase(axis, "y") ||
               http::equalsIgnoreCase(axis, "N")) {
      out.lat = value;
    } else {
      throw Error(ErrorCode::InvalidArgument, std::string(what) + ": unknown axis '" +
                                                  std::string(axis.substr(0, 20)) +
                                                  "' (the axes are Lon and Lat)");
    }
    start = close + 1;
    if (start < text.size() && text[start] == ',') {
      ++start;
    }
  }
  return out;
}

std::pair<double, double> parseRange(const std::string& text, std::string_view axis) {
  const std::size_t colon = text.find(':');
  if (colon == std::string::npos) {
    throw Error(ErrorCode::InvalidArgument,
                "subset " + std::string(axis) + " takes (low:high), not (" + text + ")");
  }
  return {number(std::string_view(text).substr(0, colon), "a subset bound"),
          number(std::string_view(text).substr(colon + 1), "a subset bound")};
}

int pixelCount(double value, std::string_view what) {
  if (value < 1 || value > 65536 || value != std::floor(value)) {
    throw Error(ErrorCode::InvalidArgument,
                std::string(what) + " must be an integer from 1 to 65536");
  }
  return static_cast<int>(value);
}

/// The picture a coverage request asks for: bbox=w,s,e,n or subset=Lon(a:b),Lat(c:d) (the whole
/// model without either), width/height or scaleSize=Lon(w),Lat(h) (else the finest spacing).
core::TopDownGrid coverageGrid(const HeightModel& m, models::PatchData& data,
                               const http::Request& request) {
  checkCrs(request.queryParam("crs"));
  checkCrs(request.queryParam("subset-crs"));
  const core::TopDownGrid whole = wholeGrid(m, data);
  core::GeoRect box{whole.x0, whole.y0 - whole.height * whole.dy, whole.x0 + whole.width * whole.dx,
                    whole.y0};
  bool boxed = false;
  if (const auto bbox = request.queryParam("bbox")) {
    double v[4];
    std::size_t at = 0;
    for (int k = 0; k < 4; ++k) {
      const std::size_t comma = k < 3 ? bbox->find(',', at) : bbox->size();
      if (comma == std::string::npos || (k == 3 && bbox->find(',', at) != std::string::npos)) {
        throw Error(ErrorCode::InvalidArgument, "bbox takes west,south,east,north in degrees");
      }
      v[k] = number(std::string_view(*bbox).substr(at, comma - at), "a bbox value");
      at = comma + 1;
    }
    box = {v[0], v[1], v[2], v[3]};
    boxed = true;
  }
  if (const auto subset = request.queryParam("subset")) {
    const AxisValues axes = parseAxes(*subset, "subset");
    if (axes.lon) {
      std::tie(box.west, box.east) = parseRange(*axes.lon, "Lon");
    }
    if (axes.lat) {
      std::tie(box.south, box.north) = parseRange(*axes.lat, "Lat");
    }
    boxed = true;
  }
  if (!(box.west < box.east) || !(box.south < box.north)) {
    throw Error(ErrorCode::InvalidArgument,
                "the box is inverted or empty: it needs west < east and south < north");
  }
  if (box.west < -180 || box.east > 180 || box.south < -90 || box.north > 90) {
    throw Error(ErrorCode::InvalidArgument,
                "the box is outside the world (longitude -180..180, latitude -90..90)");
  }
  std::optional<int> width, height;
  if (const auto w = request.queryParam("width")) {
    width = pixelCount(number(*w, "width"), "width");
  }
  if (const auto h = request.queryParam("height")) {
    height = pixelCount(number(*h, "height"), "height");
  }
  if (const auto scale = request.queryParam("scaleSize")) {
    const AxisValues axes = parseAxes(*scale, "scaleSize");
    if (axes.lon) {
      width = pixelCount(number(*axes.lon, "scaleSize Lon"), "scaleSize Lon");
    }
    if (axes.lat) {
      height = pixelCount(number(*axes.lat, "scaleSize Lat"), "scaleSize Lat");
    }
  }
  core::TopDownGrid g;
  g.geographic = true;
  g.x0 = box.west;
  g.y0 = box.north;
  if (!boxed && !width && !height) {
    g = whole;
  } else {
    const double cols =
        width ? *width : std::max(1.0, std::round((box.east - box.west) / whole.dx));
    const double rows =
        height ? *height : std::max(1.0, std::round((box.north - box.south) / whole.dy));
    if (cols * rows > static_cast<double>(kMaxCoveragePixels)) {
      throw Error(ErrorCode::InvalidArgument,
                  "the coverage would have " + std::to_string(static_cast<long long>(cols)) +
                      " x " + std::to_string(static_cast<long long>(rows)) + " pixels, more than " +
                      std::to_string(kMaxCoveragePixels) +
                      " per request; ask for a smaller box or set width and height");
    }
    g.width = static_cast<int>(cols);
    g.height = static_cast<int>(rows);
    g.dx = (box.east - box.west) / cols;
    g.dy = (box.north - box.south) / rows;
  }
  if (g.pixels() > kMaxCoveragePixels) {
    throw Error(ErrorCode::InvalidArgument,
                "the whole model at its finest resolution has " + std::to_string(g.width) + " x " +
                    std::to_string(g.height) + " pixels, more than " +
                    std::to_string(kMaxCoveragePixels) +
                    " per request; ask for a bbox or set width and height");
  }
  return g;
}

http::Response coverageAnswer(const HeightModel& m, models::PatchData& data,
                              const http::Request& request) {
  const core::TopDownGrid g = coverageGrid(m, data, request);
  char text[256];
  std::snprintf(text, sizeof text, "%.17g,%.17g,%.17g,%.17g,%d,%d", g.x0, g.y0, g.dx, g.dy, g.width,
                g.height);
  const std::string etag = viewEtag(*m.snapshot, "coverage", text);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, http::cache_control::kMinute);
  }
  // The strip's heights and paint flags and its floats, and the GeoTIFF at most as large as
  // its raw floats (deflate only shrinks them; the header is small).
  const std::size_t work = static_cast<std::size_t>(g.width) * core::StripRaster::kRows * 13 +
                           g.pixels() * sizeof(float) + (std::size_t{1} << 16);
  const std::shared_ptr<const void> charged =
      m.served.encoded->reserve(models::Encoding::HeightWork, work);
  const auto load = data.gridLoader(m.served, *m.snapshot);
  core::StripRaster raster;
  raster.width = g.width;
  raster.height = g.height;
  raster.geoTransform = {g.x0, g.dx, 0, g.y0, 0, -g.dy};
  raster.wgs84 = true;
  raster.fill = [&](int row, int rows, std::span<float> values) {
    if (request.clientGone()) {
      throw Error(ErrorCode::Cancelled, "the client of the coverage went away");
    }
    core::sampleHeightGrid(*m.snapshot->model, *m.layer, core::pictureRows(g, row, rows), load,
                           values);
  };
  const std::vector<std::byte> bytes = core::encodeCogGeoTiff(raster);
  http::Response response;
  response.status = 200;
  response.contentType = std::string(kGeoTiff);
  response.body.assign(reinterpret_cast<const char*>(bytes.data()), bytes.size());
  response.set("Content-Crs", "<" + std::string(kCrs84) + ">");
  response.set("X-VSM-Model-Version", std::to_string(m.snapshot->version));
  return withCache(std::move(response), http::cache_control::kMinute, etag);
}

// ---- OGC API ---------------------------------------------------------------------------------

json link(std::string href, std::string_view rel, std::string_view type,
          std::string_view title = {}) {
  json l = {{"href", std::move(href)}, {"rel", rel}, {"type", type}};
  if (!title.empty()) {
    l["title"] = title;
  }
  return l;
}

json domainSetJson(const core::TopDownGrid& g) {
  const double east = g.x0 + g.width * g.dx, south = g.y0 - g.height * g.dy;
  return {{"type", "DomainSet"},
          {"generalGrid",
           {{"type", "GeneralGridCoverage"},
            {"srsName", kCrs84},
            {"axisLabels", {"Lon", "Lat"}},
            {"axis",
             {{{"type", "RegularAxis"},
               {"axisLabel", "Lon"},
               {"lowerBound", g.x0},
               {"upperBound", east},
               {"uomLabel", "deg"},
               {"resolution", g.dx}},
              {{"type", "RegularAxis"},
               {"axisLabel", "Lat"},
               {"lowerBound", south},
               {"upperBound", g.y0},
               {"uomLabel", "deg"},
               {"resolution", -g.dy}}}},
            {"gridLimits",
             {{"type", "GridLimits"},
              {"srsName", "http://www.opengis.net/def/crs/OGC/0/Index2D"},
              {"axisLabels", {"i", "j"}},
              {"axis",
               {{{"type", "IndexAxis"},
                 {"axisLabel", "i"},
                 {"lowerBound", 0},
                 {"upperBound", g.width - 1}},
                {{"type", "IndexAxis"},
                 {"axisLabel", "j"},
                 {"lowerBound", 0},
                 {"upperBound", g.height - 1}}}}}}}}};
}

json rangeTypeJson() {
  return {{"type", "DataRecord"},
          {"field",
           {{{"type", "Quantity"},
             {"id", "height"},
             {"name", "height"},
             {"definition", "FLOAT32"},
             {"description", std::string("height, ") + std::string(kHeightReference)},
             {"uom", {{"type", "UnitReference"}, {"code", "m"}}},
             {"nilValues", {{{"value", "NaN"}, {"reason", "no leaf covers the pixel"}}}}}}}};
}

json collectionJson(const HeightModel& m, models::PatchData& data) {
  const core::TopDownGrid g = wholeGrid(m, data);
  const std::string base = "/ogcapi/collections/" + m.id;
  // The version in the coverage's URL: GDAL caches blocks on disk for days, by URL.
  const std::string v = "?v=" + std::to_string(m.snapshot->version);
  const core::GeoRect& b = m.layer->bounds;
  return {
      {"id", m.id},
      {"title", m.id},
      {"description", "heights of the vsm model '" + m.id + "' from its finest leaves, " +
                          std::string(kHeightReference)},
      {"itemType", "coverage"},
      {"extent", {{"spatial", {{"bbox", {{b.west, b.south, b.east, b.north}}}, {"crs", kCrs84}}}}},
      {"crs", {kCrs84}},
      {"storageCrs", kCrs84},
      {"model_version", m.snapshot->version},
      {"domainset", domainSetJson(g)},
      {"rangetype", rangeTypeJson()},
      {"links",
       {link(base + v, "self", "application/json", "this collection"),
        link(base + "/coverage" + v, "http://www.opengis.net/def/rel/ogc/1.0/coverage", kGeoTiff,
             "the heights as a GeoTIFF"),
        link(base + "/coverage/domainset" + v,
             "http://www.opengis.net/def/rel/ogc/1.0/coverage-domainset", "application/json"),
        link(base + "/coverage/rangetype" + v,
             "http://www.opengis.net/def/rel/ogc/1.0/coverage-rangetype", "application/json")}}};
}

http::Response ogcJson(json body) {
  return withCache(http::jsonResponse(200, body), http::cache_control::kRevalidate);
}

http::Response getLanding() {
  return ogcJson(
      {{"title", "vsm"},
       {"description", "Heights of the models vsmd serves, as OGC API - Coverages"},
       {"links",
        {link("/ogcapi", "self", "application/json", "this document"),
         link("/ogcapi/conformance", "conformance", "application/json", "conformance classes"),
         link("/ogcapi/collections", "data", "application/json", "the models with heights")}}});
}

http::Response getConformance() {
  return ogcJson({{"conformsTo",
                   {"http://www.opengis.net/spec/ogcapi-common-1/1.0/conf/core",
                    "http://www.opengis.net/spec/ogcapi-common-1/1.0/conf/json",
                    "http://www.opengis.net/spec/ogcapi-common-2/1.0/conf/collections",
                    "http://www.opengis.net/spec/ogcapi-coverages-1/1.0/conf/core",
                    "http://www.opengis.net/spec/ogcapi-coverages-1/1.0/conf/geotiff",
                    "http://www.opengis.net/spec/ogcapi-coverages-1/1.0/conf/subsetting",
                    "http://www.opengis.net/spec/ogcapi-coverages-1/1.0/conf/scaling"}}});
}

http::Response getCollections(models::ModelRegistry& models, models::PatchData& data,
                              const http::Request& request) {
  json collections = json::array();
  for (const std::string& id : models.ids()) {
    try {
      collections.push_back(collectionJson(heightModel(models, data, id, request), data));
    } catch (const Error& e) {
      if (e.code() != ErrorCode::NotFound) {
        throw;
      }  // closed meanwhile, empty, or no height field: not a coverage
    }
  }
  return ogcJson({{"collections", std::move(collections)},
                  {"links", {link("/ogcapi/collections", "self", "application/json")}}});
}

}  // namespace

void addGisRoutes(http::Router& router, models::ModelRegistry& models,
                  std::shared_ptr<models::PatchData> data) {
  if (data == nullptr) {
    data = std::make_shared<models::PatchData>();
  }
  for (const http::Method method : {http::Method::Get, http::Method::Post}) {
    router.add(method, "/v1/models/{m}/elevation", [&models, data](const http::Request& request) {
      return getElevation(models, *data, request);
    });
  }
  router.add(
      http::Method::Get, "/v1/models/{m}/profile",
      [&models, data](const http::Request& request) { return getProfile(models, *data, request); });
  router.add(http::Method::Get, "/v1/models/{m}/coverage",
             [&models, data](const http::Request& request) {
               return coverageAnswer(heightModel(models, *data, request.param("m"), request), *data,
                                     request);
             });
  router.add(http::Method::Get, "/ogcapi", [](const http::Request&) { return getLanding(); });
  router.add(http::Method::Get, "/ogcapi/conformance",
             [](const http::Request&) { return getConformance(); });
  router.add(http::Method::Get, "/ogcapi/collections",
             [&models, data](const http::Request& request) {
               return getCollections(models, *data, request);
             });
  router.add(http::Method::Get, "/ogcapi/collections/{m}",
             [&models, data](const http::Request& request) {
               return ogcJson(
                   collectionJson(heightModel(models, *data, request.param("m"), request), *data));
             });
  router.add(http::Method::Get, "/ogcapi/collections/{m}/coverage",
             [&models, data](const http::Request& request) {
               return coverageAnswer(heightModel(models, *data, request.param("m"), request), *data,
                                     request);
             });
  router.add(http::Method::Get, "/ogcapi/collections/{m}/coverage/domainset",
             [&models, data](const http::Request& request) {
               return ogcJson(domainSetJson(
                   wholeGrid(heightModel(models, *data, request.param("m"), request), *data)));
             });
  router.add(http::Method::Get, "/ogcapi/collections/{m}/coverage/rangetype",
             [](const http::Request&) { return ogcJson(rangeTypeJson()); });
}

}  // namespace vsm::server::api
