#pragma once

#include <memory>

#include "server/http/router.hpp"

namespace vsm::server::models {
class ModelRegistry;
class PatchData;
}  // namespace vsm::server::models

namespace vsm::server::api {

/// Heights for GIS and web-map clients, from every open model that is a height field over the
/// WGS 84 ellipsoid (the models that have quantized-mesh terrain), all sampled from the finest
/// leaves by the one height sampler the terrain tiles use (core/tiles/heights.hpp):
///
/// - GET or POST /v1/models/{m}/elevation: Open Topo Data's request (`locations=lat,lon|...`,
///   `samples=N` along the path) and answer (`status`, `results` with `elevation` and
///   `location`), plus the depth and resolution that answered each point; a GeoJSON Point,
///   MultiPoint or LineString body is accepted too;
/// - GET /v1/models/{m}/profile?line=lat,lon|...[&samples=N]: heights along the line, with their
///   distances, at the finest resolution by default;
/// - GET /v1/models/{m}/coverage?bbox=w,s,e,n&width=W&height=H: a float32 GeoTIFF (COG layout,
///   NaN no-data) of an area;
/// - OGC API - Coverages for GDAL's OGCAPI driver and QGIS: /ogcapi (landing page),
///   /ogcapi/conformance, /ogcapi/collections, /ogcapi/collections/{m} (with its domain set and
///   range type) and /ogcapi/collections/{m}/coverage (`subset=Lon(a:b),Lat(c:d)`,
///   `scaleSize=Lon(w),Lat(h)`).
///
/// All take `?rev=` and `?v=` (versionedSnapshot). Bounded: 1000 points per elevation request,
/// 10000 profile samples, 4096 x 4096 pixels per coverage, whose working memory is charged to the
/// budget (Encoding::HeightWork) while it is made. Pool only. See proto/openapi.yaml.
void addGisRoutes(http::Router& router, models::ModelRegistry& models,
                  std::shared_ptr<models::PatchData> data);

}  // namespace vsm::server::api
