// server/api: the diff gate, system and static routes, and the model, job and ray routes
// through the real Router and Pipeline (no sockets) over a synthetic OPC in a temporary data root.
#include <gtest/gtest.h>

#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <span>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/validate.hpp"
#include "core/store/live_model.hpp"
#include "core/store/model_edit.hpp"
#include "server/api/diff_gate.hpp"
#include "server/api/job_routes.hpp"
#include "server/api/model_routes.hpp"
#include "server/api/ray_routes.hpp"
#include "server/api/static_routes.hpp"
#include "server/api/system_routes.hpp"
#include "server/api/terrain_routes.hpp"
#include "server/api/tiles_routes.hpp"
#include "server/exec/work_pool.hpp"
#include "server/http/pipeline.hpp"
#include "server/http/router.hpp"
#include "server/jobs/job_registry.hpp"
#include "server/jobs/model_jobs.hpp"
#include "server/metrics/metrics.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"
#include "tests/unit/server_test_support.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::server {
namespace {

namespace fs = std::filesystem;
using core::Error;
using core::ErrorCode;
using core::test::errorOf;
using nlohmann::json;
using namespace std::chrono_literals;
using test::bytesOf;
using test::DataRoot;
using test::kMiB;
using test::kSize;
using test::leafGrid;
using test::request;
using test::waitFinal;
using test::writeModel;

// --- diff gate ------------------------------------------------------------------------------

TEST(DiffGate, RefusesBeyondItsSlotsAndFreesASlotWhenItsDiffEnds) {
  const auto gate = api::DiffGate::create({2, std::chrono::milliseconds(0)});
  auto first = gate->enter();
  auto second = gate->enter();
  EXPECT_EQ(first->deadline(), std::chrono::steady_clock::time_point::max()) << "no deadline";
  try {
    gate->enter();
    ADD_FAILURE() << "a third diff entered a gate of two";
  } catch (const core::Error& e) {
    EXPECT_EQ(e.code(), core::ErrorCode::Unavailable);  // 503 with Retry-After
  }
  EXPECT_EQ(gate->stats().running, 2u);
  EXPECT_EQ(gate->stats().refused, 1u);
  first.reset();
  EXPECT_NE(gate->enter(), nullptr);
  EXPECT_EQ(gate->stats().running, 1u);
  const auto timed = api::DiffGate::create({1, std::chrono::minutes(1)});
  const auto before = std::chrono::steady_clock::now();
  EXPECT_GE(timed->enter()->deadline(), before + std::chrono::minutes(1));
  EXPECT_EQ(api::DiffGate::create({0, {}})->stats().slots, 0u);
  EXPECT_THROW(api::DiffGate::create({0, {}})->enter(), core::Error);
}

// --- system routes --------------------------------------------------------------------------

TEST(SystemRoutes, StatsReportTheBudgetAndEveryCategory) {
  const core::PatchCache cache(64 * kMiB);
  const json stats = api::statsJson(cache.stats(), cache.policy());
  EXPECT_EQ(stats.at("memory").at("budget_bytes"), 64 * kMiB);
  EXPECT_EQ(stats.at("memory").at("resident_bytes"), 0);
  EXPECT_EQ(stats.at("memory").at("resident_bytes_by_category").size(), core::kMemoryCategoryCount);
  EXPECT_EQ(stats.at("memory").at("encoded_bytes_by_encoding"), json({{"aara", 0},
                                                                      {"glb", 0},
                                                                      {"png", 0},
                                                                      {"terrain", 0},
                                                                      {"glb_meshopt", 0},
                                                                      {"json_gzip", 0},
                                                                      {"diff", 0},
                                                                      {"heights", 0},
                                                                      {"terrain_rgb", 0},
                                                                      {"rays", 0}}));
  EXPECT_TRUE(stats.at("memory").at("resident_bytes_by_model").is_object());
  for (const char* key : {"hits", "misses", "evictions", "write_backs", "exhausted"}) {
    EXPECT_EQ(stats.at("cache").at(key), 0) << key;
  }
  EXPECT_EQ(stats.at("cache").at("policy"), "cost-aware-clock");
}

TEST(SystemRoutes, ReadinessFollowsTheFlag) {
  const core::PatchCache cache(64 * kMiB);
  const metrics::Registry registry;
  bool ready = false;
  http::Router router;
  api::addSystemRoutes(router, {cache, registry, [&] { return ready; }});
  const http::Pipeline pipeline(router, "");
  auto r = request(http::Method::Get, "/readyz");
  EXPECT_EQ(pipeline.handle(r).response.status, 503);
  ready = true;
  EXPECT_EQ(pipeline.handle(r).response.status, 200);
}

// --- static files (the viewer at /viewer/) -------------------------------------------------

/// A viewer directory with an index, a nested module, a hidden file, a link inside the tree and
/// links out of it, next to a secret that must never be served.
class StaticFiles : public core::test::TempDirTest {
 protected:
  StaticFiles() : TempDirTest("static") {}
  void SetUp() override {
    root_ = base_ / "viewer";
    std::filesystem::create_directories(root_ / "vendor" / "three");
    std::filesystem::create_directories(base_ / "viewer-secrets");
    write(root_ / "index.html", "<!doctype html>");
    write(root_ / "vendor" / "three" / "three.module.js", "export {};");
    write(root_ / ".hidden", "no");
    write(base_ / "secret.txt", "secret");
    write(base_ / "viewer-secrets" / "key.txt", "secret");
    std::filesystem::create_symlink(root_ / "index.html", root_ / "inside.html");
    std::filesystem::create_symlink(base_ / "secret.txt", root_ / "out.txt");
    std::filesystem::create_directory_symlink(base_, root_ / "up");
    root_ = std::filesystem::canonical(root_);
  }
  static void write(const std::filesystem::path& path, const std::string& text) {
    std::ofstream(path, std::ios::binary) << text;
  }

  const std::filesystem::path& base_ = dir_;
  std::filesystem::path root_;
};

TEST_F(StaticFiles, ResolvesFilesAndDirectoryIndexesInsideTheRoot) {
  EXPECT_EQ(api::resolveStaticFile(root_, ""), root_ / "index.html");
  EXPECT_EQ(api::resolveStaticFile(root_, "index.html"), root_ / "index.html");
  EXPECT_EQ(api::resolveStaticFile(root_, "vendor/three/three.module.js"),
            root_ / "vendor" / "three" / "three.module.js");
  // A link inside the tree is followed.
  EXPECT_EQ(api::resolveStaticFile(root_, "inside.html"), root_ / "index.html");
}

TEST_F(StaticFiles, RefusesTraversalHiddenFilesLinksOutAndDirectories) {
  for (const char* path :
       {"..", "../secret.txt", "vendor/../../secret.txt", "./index.html", "vendor/./three", "a//b",
        "/index.html", ".hidden", "out.txt", "up/secret.txt", "../viewer-secrets/key.txt", "vendor",
        "vendor/three", "missing.js", "vendor\\..\\x"}) {
    EXPECT_EQ(api::resolveStaticFile(root_, path), std::nullopt) << path;
  }
  EXPECT_EQ(api::resolveStaticFile(root_, std::string("index.html\0x", 12)), std::nullopt);
  EXPECT_EQ(api::resolveStaticFile(root_, std::string(2000, 'a')), std::nullopt);
}

TEST_F(StaticFiles, AreServedWithTypesETagsRedirectsAnd404s) {
  http::Router router;
  api::addStaticRoutes(router, "/viewer", base_ / "viewer");
  const http::Pipeline pipeline(router, "");

  http::Request r = request(http::Method::Get, "/viewer/?model=merged");
  http::Handled handled = pipeline.handle(r);
  EXPECT_EQ(handled.response.status, 200);
  EXPECT_EQ(handled.response.bodyText(), "<!doctype html>");
  EXPECT_EQ(handled.response.contentType, "text/html; charset=utf-8");
  ASSERT_NE(handled.response.header("ETag"), nullptr);
  const std::string etag = *handled.response.header("ETag");
  r = request(http::Method::Get, "/viewer/index.html");
  r.headers.emplace_back("if-none-match", etag);
  EXPECT_EQ(pipeline.handle(r).response.status, 304);

  r = request(http::Method::Get, "/viewer/vendor/three/three.module.js");
  EXPECT_EQ(pipeline.handle(r).response.contentType, "text/javascript; charset=utf-8");

  r = request(http::Method::Get, "/viewer?model=merged");
  handled = pipeline.handle(r);
  EXPECT_EQ(handled.response.status, 301);
  ASSERT_NE(handled.response.header("Location"), nullptr);
  EXPECT_EQ(*handled.response.header("Location"), "/viewer/?model=merged");

  for (const char* target : {"/viewer/../secret.txt", "/viewer/%2e%2e/secret.txt",
                             "/viewer/vendor%2F..%2F..%2Fsecret.txt", "/viewer/out.txt",
                             "/viewer/up/secret.txt", "/viewer/nope.js"}) {
    r = request(http::Method::Get, target);
    handled = pipeline.handle(r);
    EXPECT_EQ(handled.response.status, 404) << target;
    EXPECT_NE(handled.response.bodyText(), "secret") << target;
  }
  EXPECT_EQ(errorOf([&] { api::addStaticRoutes(router, "/x", base_ / "none"); }).first,
            ErrorCode::NotFound);
}

TEST(StaticContentType, FollowsTheExtension) {
  EXPECT_EQ(api::staticContentType("a/index.html"), "text/html; charset=utf-8");
  EXPECT_EQ(api::staticContentType("main.js"), "text/javascript; charset=utf-8");
  EXPECT_EQ(api::staticContentType("x.MJS"), "text/javascript; charset=utf-8");
  EXPECT_EQ(api::staticContentType("widgets.css"), "text/css; charset=utf-8");
  EXPECT_EQ(api::staticContentType("a.json"), "application/json");
  EXPECT_EQ(api::staticContentType("draco.wasm"), "application/wasm");
  EXPECT_EQ(api::staticContentType("LICENSE"), "application/octet-stream");
}

// ---- routes ----------------------------------------------------------------------------------

/// The model and job routes over a data root holding the synthetic model as "m".
class ModelRoutes : public ::testing::Test {
 protected:
  ModelRoutes() {
    writeModel(root_.path() / "m");
    registry_.openAll();
    api::addModelRoutes(router_, {registry_, jobs_});
    api::addJobRoutes(router_, {registry_, jobs_});
  }
  ~ModelRoutes() override { pool_.join(); }

  http::Response get(std::string target, std::string ifNoneMatch = {}) {
    auto r = request(http::Method::Get, std::move(target));
    if (!ifNoneMatch.empty()) {
      r.headers.emplace_back("if-none-match", ifNoneMatch);
    }
    return pipeline_.handle(r).response;
  }
  http::Response send(http::Method method, std::string target, std::string body = {}) {
    auto r = request(method, std::move(target), std::move(body));
    return pipeline_.handle(r).response;
  }
  static std::string codeOf(const http::Response& response) {
    return json::parse(response.body).at("error").at("code");
  }

  DataRoot root_;
  core::PatchCache cache_{64 * kMiB};
  models::ModelRegistry registry_{root_.path(), cache_};
  exec::WorkPool pool_{"jobs", 1};
  exec::WorkPool helpers_{"job-helpers", 1};
  jobs::JobRegistry jobs_{pool_, helpers_};
  http::Router router_;
  http::Pipeline pipeline_{router_, ""};
};

TEST_F(ModelRoutes, ListAndSummaryDescribeTheModel) {
  const auto list = get("/v1/models");
  EXPECT_EQ(list.status, 200);
  EXPECT_EQ(*list.header("Cache-Control"), "no-cache");
  const json models = json::parse(list.body).at("models");
  ASSERT_EQ(models.size(), 1u);
  EXPECT_EQ(models[0].at("id"), "m");
  EXPECT_FALSE(models[0].contains("levels"));

  const auto summary = get("/v1/models/m");
  EXPECT_EQ(summary.status, 200);
  const json body = json::parse(summary.body);
  EXPECT_EQ(body.at("grid_size"), kSize);
  EXPECT_EQ(body.at("depth"), 2);
  EXPECT_EQ(body.at("patches"), 20);
  EXPECT_EQ(body.at("leaves"), 15);
  EXPECT_EQ(body.at("levels").size(), 3u);
  EXPECT_EQ(body.at("bounds").at("min").at(0), 0.0);
  EXPECT_EQ(body.at("bounds").at("max").at(0), 64.0);
  EXPECT_NEAR(body.at("resolution").at("finest").get<double>(), 1.0, 0.2);

  const std::string etag = *summary.header("ETag");
  EXPECT_EQ(etag.front(), '"');
  const auto again = get("/v1/models/m", etag);
  EXPECT_EQ(again.status, 304);
  EXPECT_TRUE(again.body.empty());
  EXPECT_EQ(get("/v1/models/m", "\"other\"").status, 200);
  EXPECT_EQ(get("/v1/models/nope").status, 404);
  EXPECT_EQ(get("/v1/models/..").status, 404);
}

TEST_F(ModelRoutes, HierarchyIsATreeCutAtTheRequestedDepth) {
  const json full = json::parse(get("/v1/models/m/hierarchy").body);
  EXPECT_EQ(full.at("root").at("key"), "0_0_0");
  ASSERT_EQ(full.at("root").at("children").size(), 4u);
  EXPECT_EQ(full.at("root").at("children")[3].at("children").size(), 3u);  // 3_3 is absent
  const json top = json::parse(get("/v1/models/m/hierarchy?depth=0").body);
  EXPECT_FALSE(top.at("root").contains("children"));
  EXPECT_EQ(top.at("root").at("child_count"), 4);
  const json sub = json::parse(get("/v1/models/m/hierarchy?root=1_1_0&depth=1").body);
  EXPECT_EQ(sub.at("root").at("children").size(), 4u);
  EXPECT_TRUE(sub.at("root").at("children")[0].at("leaf"));
  EXPECT_EQ(get("/v1/models/m/hierarchy?root=1_5_0").status, 400);  // x out of range
  EXPECT_EQ(get("/v1/models/m/hierarchy?root=2_3_3").status, 404);
  EXPECT_EQ(get("/v1/models/m/hierarchy?depth=-1").status, 400);
  EXPECT_EQ(get("/v1/models/m/hierarchy?depth=x").status, 400);
  const auto first = get("/v1/models/m/hierarchy?depth=1");
  EXPECT_NE(*first.header("ETag"), *get("/v1/models/m/hierarchy").header("ETag"));
  EXPECT_EQ(get("/v1/models/m/hierarchy?depth=1", *first.header("ETag")).status, 304);
}

TEST_F(ModelRoutes, PatchMetadataAndPositionsComeFromOneVersion) {
  const auto meta = get("/v1/models/m/patches/2_1_2");
  ASSERT_EQ(meta.status, 200) << meta.body;
  const json patch = json::parse(meta.body);
  EXPECT_EQ(patch.at("key"), "2_1_2");
  EXPECT_EQ(patch.at("parent"), "1_0_1");
  EXPECT_TRUE(patch.at("children").empty());
  EXPECT_EQ(patch.at("local2global").size(), 16u);
  EXPECT_EQ(patch.at("stored").at("x1"), kSize);
  EXPECT_EQ(*meta.header("Cache-Control"), "public, max-age=60");

  const auto data = get("/v1/models/m/patches/2_1_2/positions");
  ASSERT_EQ(data.status, 200) << data.body;
  EXPECT_EQ(data.contentType, "application/octet-stream");
  EXPECT_EQ(*data.header("ETag"), *meta.header("ETag"));
  EXPECT_EQ(*data.header("X-VSM-Local2Global"), "1,0,0,24,0,1,0,40,0,0,1,0,0,0,0,1");
  EXPECT_EQ(data.bodySize(), 13u + kSize * kSize * 12u);
  // Stored uncropped as V3f: the stored file itself is the body, sent with sendfile(2).
  EXPECT_GE(data.file.fd, 0);
  EXPECT_EQ(data.file.size, data.bodySize());
  EXPECT_TRUE(data.body.empty());
  const std::string bytes = data.bodyText();
  const core::AaraArray array =
      core::decodeAara(std::as_bytes(std::span(bytes.data(), bytes.size())), "response");
  EXPECT_EQ(array.type, core::AaraType::V3f);
  EXPECT_EQ(array.sizes, (std::vector<std::int32_t>{kSize, kSize}));
  float first[3];
  std::memcpy(first, array.data.data(), sizeof first);
  EXPECT_EQ(first[0], -8.0f);  // global (16, 32) minus the origin (24, 40)
  EXPECT_EQ(first[1], -8.0f);

  EXPECT_EQ(get("/v1/models/m/patches/2_1_2/positions", *data.header("ETag")).status, 304);
  EXPECT_EQ(get("/v1/models/m/patches/2_3_3").status, 404);
  EXPECT_EQ(get("/v1/models/m/patches/2_3_3/positions").status, 404);
  EXPECT_EQ(get("/v1/models/m/patches/nonsense").status, 400);
  EXPECT_EQ(get("/v1/models/m/patches/1_1").status, 400);
  EXPECT_EQ(get("/v1/models/x/patches/0_0_0").status, 404);
}

TEST_F(ModelRoutes, LodStopsAtTheTargetResolutionOrALeafInsideTheBox) {
  const auto coarse = json::parse(get("/v1/models/m/lod?box=0,0,-10,64,64,10&resolution=100").body);
  ASSERT_EQ(coarse.at("patches").size(), 1u);
  EXPECT_EQ(coarse.at("patches")[0].at("key"), "0_0_0");
  const auto fine = json::parse(get("/v1/models/m/lod?box=0,0,-10,64,64,10&resolution=0.5").body);
  EXPECT_EQ(fine.at("patches").size(), 15u);
  // A corner box: only the patches that meet it, at the finest level.
  const auto corner = json::parse(get("/v1/models/m/lod?box=1,1,-10,2,2,10&resolution=0.5").body);
  ASSERT_EQ(corner.at("patches").size(), 1u);
  EXPECT_EQ(corner.at("patches")[0].at("key"), "2_0_0");
  const auto mid = json::parse(get("/v1/models/m/lod?box=0,0,-10,64,64,10&resolution=2.5").body);
  EXPECT_EQ(mid.at("patches").size(), 4u);
  EXPECT_EQ(mid.at("patches")[0].at("key"), "1_0_0");
  const auto outside =
      json::parse(get("/v1/models/m/lod?box=100,100,0,200,200,1&resolution=1").body);
  EXPECT_TRUE(outside.at("patches").empty());
  for (const char* bad : {"/v1/models/m/lod", "/v1/models/m/lod?box=0,0,0,1,1,1",
                          "/v1/models/m/lod?box=0,0,0,1,1&resolution=1",
                          "/v1/models/m/lod?box=0,0,0,1,1,1,1&resolution=1",
                          "/v1/models/m/lod?box=1,0,0,0,1,1&resolution=1",
                          "/v1/models/m/lod?box=0,0,0,1,1,nan&resolution=1",
                          "/v1/models/m/lod?box=0,0,0,1,1,1&resolution=0",
                          "/v1/models/m/lod?box=0,0,0,1,1,1x&resolution=1",
                          "/v1/models/m/lod?box=0,0,0,1,1,1&resolution=-2"}) {
    const auto response = get(bad);
    EXPECT_EQ(response.status, 400) << bad;
    EXPECT_EQ(codeOf(response), "invalid_argument");
  }
}

TEST_F(ModelRoutes, RaysAnswerTheFirstHitOnTheLeavesAsJson) {
  api::addRayRoutes(router_, registry_, nullptr);
  // The synthetic surface is z = 5 sin(x / 5) on a 1 m lattice: bilinear in x within a cell.
  const auto surface = [](double x) {
    const double x0 = std::floor(x), s = x - x0;
    return 5 * ((1 - s) * std::sin(x0 * 0.2) + s * std::sin((x0 + 1) * 0.2));
  };
  const auto down = get("/v1/models/m/ray?origin=10.5,3.5,20&direction=0,0,-2");
  ASSERT_EQ(down.status, 200) << down.bodyText();
  const json answer = json::parse(down.body);
  EXPECT_EQ(*down.header("X-VSM-Model-Version"),
            std::to_string(answer.at("model_version").get<int>()));
  EXPECT_EQ(answer.at("status"), "OK");
  EXPECT_EQ(answer.at("model"), "m");
  const json& hit = answer.at("results").at(0).at("hit");
  const double z = surface(10.5);
  EXPECT_NEAR(hit.at("point")[0].get<double>(), 10.5, 1e-9);
  EXPECT_NEAR(hit.at("point")[1].get<double>(), 3.5, 1e-9);
  EXPECT_NEAR(hit.at("point")[2].get<double>(), z, 1e-5);
  EXPECT_NEAR(hit.at("distance").get<double>(), 20 - z, 1e-5);
  // The cell's slope along x, the normal facing up (the ray came from above).
  const double slope = 5 * (std::sin(2.2) - std::sin(2.0));
  const double length = std::hypot(slope, 1.0);
  EXPECT_NEAR(hit.at("normal")[0].get<double>(), -slope / length, 1e-5);
  EXPECT_NEAR(hit.at("normal")[1].get<double>(), 0, 1e-5);
  EXPECT_NEAR(hit.at("normal")[2].get<double>(), 1 / length, 1e-5);
  EXPECT_EQ(hit.at("patch"), "2_0_0");
  EXPECT_EQ(hit.at("depth"), 2);
  EXPECT_GT(hit.at("resolution").get<double>(), 0.9);

  // POST: the same ray, one into the model's hole (leaf 2_3_3 is missing) and one cut short.
  const auto posted = send(http::Method::Post, "/v1/models/m/ray",
                           R"({"rays": [{"origin": [10.5, 3.5, 20], "direction": [0, 0, -2]},
                                        {"origin": [56, 56, 20], "direction": [0, 0, -1]},
                                        {"origin": [10.5, 3.5, 20], "direction": [0, 0, -1],
                                         "max_distance": 10}]})");
  ASSERT_EQ(posted.status, 200) << posted.bodyText();
  const json results = json::parse(posted.body).at("results");
  ASSERT_EQ(results.size(), 3u);
  EXPECT_EQ(results[0], answer.at("results")[0]);
  EXPECT_TRUE(results[1].at("hit").is_null());
  EXPECT_TRUE(results[2].at("hit").is_null());

  const auto bad = send(http::Method::Post, "/v1/models/m/ray",
                        R"({"rays": [{"origin": [1, 2, 3], "direction": [0, 0, 1]},
                                     {"origin": [1, 2, 3], "direction": [0, 0, 0]}]})");
  EXPECT_EQ(bad.status, 400);
  EXPECT_EQ(codeOf(bad), "invalid_argument");
  EXPECT_NE(bad.bodyText().find("ray 2: 'direction' must not be zero"), std::string::npos)
      << bad.bodyText();
  EXPECT_EQ(get("/v1/models/m/ray?origin=1,2,3&direction=0,0").status, 400);
  EXPECT_EQ(get("/v1/models/none/ray?origin=1,2,3&direction=0,0,1").status, 404);
}

TEST_F(ModelRoutes, OpenByPathCloseAndPathTricks) {
  writeModel(root_.path() / "nested" / "copy");
  const auto opened = send(http::Method::Post, "/v1/models",
                           R"({"id": "copy", "source": {"path": "nested/copy"}})");
  ASSERT_EQ(opened.status, 201) << opened.body;
  EXPECT_EQ(*opened.header("Location"), "/v1/models/copy");
  EXPECT_EQ(json::parse(opened.body).at("patches"), 20);
  EXPECT_EQ(
      send(http::Method::Post, "/v1/models", R"({"id": "copy", "source": {"path": "nested/copy"}})")
          .status,
      409);
  EXPECT_EQ(
      send(http::Method::Post, "/v1/models", R"({"id": "again", "source": {"path": "m"}})").status,
      409);
  const DataRoot outside;
  writeModel(outside.path() / "o");
  fs::create_directory_symlink(outside.path() / "o", root_.path() / "link");
  for (const char* body :
       {R"({"id": "x", "source": {"path": "../x"}})", R"({"id": "x", "source": {"path": "/tmp"}})",
        R"({"id": "x", "source": {"path": "link"}})", R"({"id": "x", "source": {"path": ""}})",
        R"({"id": "x", "source": {"path": "."}})", R"({"id": "../x", "source": {"path": "m"}})",
        R"({"id": "a/b", "source": {"path": "m"}})", R"({"id": "x", "source": {"import": "../a"}})",
        R"({"id": "x", "source": {"import": "/etc/passwd", "patch_size": 65}})",
        R"({"id": "x", "source": {"path": "m", "import": "a"}})", R"({"id": "x"})",
        R"({"id": 5, "source": {"path": "m"}})", R"({"id": "x", "source": {"path": "m"}, "y": 1})",
        R"({"id": "x", "source": {"import": "a.tif", "patch_size": 64}})", "[1]", "not json"}) {
    const auto response = send(http::Method::Post, "/v1/models", body);
    EXPECT_EQ(response.status, 400) << body << " -> " << response.body;
  }
  EXPECT_EQ(
      send(http::Method::Post, "/v1/models", R"({"id": "x", "source": {"path": "none"}})").status,
      404);
  EXPECT_EQ(registry_.size(), 2u);
  EXPECT_EQ(send(http::Method::Delete, "/v1/models/copy").status, 204);
  EXPECT_EQ(send(http::Method::Delete, "/v1/models/copy").status, 404);
  EXPECT_EQ(get("/v1/models/copy").status, 404);
  EXPECT_TRUE(fs::exists(root_.path() / "nested" / "copy" / "Patches"));
}

TEST_F(ModelRoutes, JobRoutesValidateAndReportMergeJobs) {
  for (const char* body :
       {R"({"type": "merge", "target": "m"})", R"({"type": "nope", "target": "m", "source": "m"})",
        R"({"type": "merge", "target": "m", "source": "m"})",
        R"({"type": "merge", "target": "m", "source": "s", "x": 1})",
        R"({"type": "merge", "target": "m", "source": "s", "register": 1})"}) {
    EXPECT_EQ(send(http::Method::Post, "/v1/jobs", body).status, 400) << body;
  }
  EXPECT_EQ(send(http::Method::Post, "/v1/jobs",
                 R"({"type": "merge", "target": "m", "source": "absent"})")
                .status,
            404);
  EXPECT_EQ(get("/v1/jobs/absent").status, 404);
  EXPECT_EQ(send(http::Method::Delete, "/v1/jobs/absent").status, 404);
  EXPECT_EQ(json::parse(get("/v1/jobs").body).at("jobs").size(), 0u);
}

// Issue 32, finding 2: a job's commit is fenced (in a cluster, by the node's lease).
TEST_F(ModelRoutes, AFencedCommitIsRefusedAndLeavesTheModelAsItWas) {
  std::shared_ptr<core::LiveModel> live = registry_.get("m");
  const std::uint64_t v = live->snapshot()->version;
  {
    auto edit = live->beginEdit();
    edit->setPositions({2, 1, 2}, leafGrid(1, 2));
    edit->publish();
  }
  const fs::path hierarchy = root_.path() / "m" / "Patches" / "patchhierarchy.xml";
  const auto before = core::hierarchyStamp(root_.path() / "m");
  std::atomic<bool> holds{false};
  std::atomic<int> asked{0};
  models::ModelRegistry::WriterFence fence;
  fence.token = [](std::string_view) { return core::FencingToken{42, 7}; };
  fence.check = [&](std::string_view id, const std::optional<core::FencingToken>& token) {
    EXPECT_EQ(id, "m");
    EXPECT_EQ(token, (core::FencingToken{42, 7})) << "the token the write began under";
    ++asked;
    if (!holds) {
      throw core::Error(core::ErrorCode::Conflict, "node a is no longer the writer of model 'm'");
    }
  };
  registry_.fenceWrites(std::move(fence));
  const auto refused = waitFinal(jobs_, jobs::submitRestore(jobs_, registry_, "m", v).id);
  EXPECT_EQ(refused.state, jobs::JobState::Failed);
  EXPECT_EQ(refused.errorCode, core::ErrorCode::Conflict);
  EXPECT_EQ(asked, 1);
  EXPECT_EQ(core::hierarchyStamp(root_.path() / "m"), before)
      << "a refused commit changed the model";
  EXPECT_EQ(registry_.get("m")->snapshot()->version, v + 1);
  EXPECT_TRUE(core::validateOpc(root_.path() / "m").empty());
  holds = true;
  const auto done = waitFinal(jobs_, jobs::submitRestore(jobs_, registry_, "m", v).id);
  EXPECT_EQ(done.state, jobs::JobState::Succeeded) << done.errorMessage;
  EXPECT_EQ(registry_.get("m")->snapshot()->version, v + 2);
  EXPECT_TRUE(fs::exists(hierarchy));
  EXPECT_EQ(core::readRevisionRecord(hierarchy)->fence, (core::FencingToken{42, 7}))
      << "the job's revision records its writer's token";
}

/// The model routes with the 3D Tiles and terrain routes, over "m" at version 2 (every patch
/// written at version 2).
class VersionedReads : public ModelRoutes {
 protected:
  VersionedReads() {
    api::addTilesRoutes(router_, registry_);
    api::addTerrainRoutes(router_, registry_);
  }

  /// Publishes version 3: leaf 2_1_2 and its ancestors rewritten, every other patch still of
  /// version 2 (revision 2 kept).
  void publish() {
    auto edit = registry_.get("m")->beginEdit();
    edit->setPositions({2, 1, 2}, leafGrid(1, 2));
    edit->publish();
  }

  /// Every read route that takes ?v=, with `query` ("v=N..."): each answers from one version.
  static std::vector<std::string> routes(const std::string& patch, const std::string& query) {
    std::vector<std::string> out;
    for (const std::string& path : std::vector<std::string>{
             "/v1/models/m", "/v1/models/m/hierarchy", "/v1/models/m/patches/" + patch,
             "/v1/models/m/patches/" + patch + "/positions",
             "/v1/models/m/patches/" + patch + "/coordinates",
             "/v1/models/m/patches/" + patch + "/texture",
             "/v1/models/m/patches/" + patch + "/texture/Diffuse",
             "/v1/models/m/3dtiles/tileset.json", "/v1/models/m/3dtiles/" + patch + ".glb",
             "/v1/models/m/terrain/layer.json", "/v1/models/m/terrain/0/0/0.terrain"}) {
      out.push_back(path + "?" + query);
    }
    out.push_back("/v1/models/m/lod?box=0,0,-10,64,64,10&resolution=100&" + query);
    return out;
  }
};

TEST_F(VersionedReads, AVersionNewerThanTheServedOneIsA404NoCacheKeeps) {
  ASSERT_EQ(json::parse(get("/v1/models/m").body).at("version"), 2);
  for (const std::string patch : {"2_1_2", "2_0_0"}) {
    for (const std::string& target : routes(patch, "v=999")) {
      const auto response = get(target);
      EXPECT_EQ(*response.header("Cache-Control"), "no-store") << target;
      if (response.status != 404) {
        ADD_FAILURE() << target << " answered " << response.status << ", not 404";
        continue;
      }
      const json error = json::parse(response.body).at("error");
      EXPECT_EQ(error.at("code"), "not_found") << target;
      const std::string message = error.at("message");
      EXPECT_NE(message.find("version 999"), std::string::npos) << target << ": " << message;
      EXPECT_NE(message.find("serves version 2"), std::string::npos) << target << ": " << message;
    }
  }
  // With ?rev=, only that revision's version answers.
  publish();
  for (const std::string& target : routes("2_1_2", "v=2&rev=3")) {
    const auto response = get(target);
    EXPECT_EQ(response.status, 404) << target;
    EXPECT_EQ(*response.header("Cache-Control"), "no-store") << target;
  }
  for (const std::string& target : routes("2_1_2", "v=x")) {
    EXPECT_EQ(get(target).status, 400) << target;
  }
}

TEST_F(VersionedReads, EveryVersionThatHoldsAPatchAsServedAnswersIt) {
  publish();
  ASSERT_EQ(json::parse(get("/v1/models/m").body).at("version"), 3);
  // 2_0_0 is of version 2 in version 3: both versions name the same bytes.
  const auto current = get("/v1/models/m/patches/2_0_0/positions");
  ASSERT_EQ(current.status, 200);
  for (const char* query : {"?v=2", "?v=3", "?v=3&rev=3"}) {
    const auto response = get(std::string("/v1/models/m/patches/2_0_0/positions") + query);
    ASSERT_EQ(response.status, 200) << query << response.body;
    EXPECT_EQ(response.bodyText(), current.bodyText()) << query;
    EXPECT_EQ(*response.header("X-VSM-Patch-Version"), "2") << query;
    EXPECT_EQ(get(std::string("/v1/models/m/3dtiles/2_0_0.glb") + query).status, 200) << query;
  }
  // 2_1_2 was rewritten by version 3: ?v=2 is answered from kept revision 2, ?v=3 now; version 1
  // was never kept.
  const auto old = get("/v1/models/m/patches/2_1_2/positions?v=2");
  ASSERT_EQ(old.status, 200) << old.body;
  EXPECT_EQ(*old.header("X-VSM-Patch-Version"), "2");
  EXPECT_EQ(*old.header("X-VSM-Model-Version"), "2");
  EXPECT_EQ(old.bodyText(), get("/v1/models/m/patches/2_1_2/positions?rev=2").bodyText());
  EXPECT_EQ(*get("/v1/models/m/patches/2_1_2/positions?v=3").header("X-VSM-Patch-Version"), "3");
  EXPECT_EQ(get("/v1/models/m/patches/2_1_2?v=2&rev=3").status, 404);
  const auto gone = get("/v1/models/m/patches/2_1_2/positions?v=1");
  EXPECT_EQ(gone.status, 404);
  EXPECT_EQ(*gone.header("Cache-Control"), "no-store");
  // Documents: exactly their version, the current one or a kept revision.
  EXPECT_EQ(json::parse(get("/v1/models/m?v=3").body).at("version"), 3);
  EXPECT_EQ(json::parse(get("/v1/models/m?v=2").body).at("version"), 2);
  EXPECT_EQ(json::parse(get("/v1/models/m/hierarchy?v=2").body).at("version"), 2);
  EXPECT_EQ(get("/v1/models/m?v=1").status, 404);
  // The tileset names its version, and its links the version that wrote each patch.
  const json tileset = json::parse(get("/v1/models/m/3dtiles/tileset.json").body);
  EXPECT_EQ(tileset.at("asset").at("extras").at("model_version"), 3);
  EXPECT_EQ(tileset.at("root").at("content").at("uri"), "0_0_0.glb?v=3");
  const json oldTileset = json::parse(get("/v1/models/m/3dtiles/tileset.json?v=2").body);
  EXPECT_EQ(oldTileset.at("asset").at("extras").at("model_version"), 2);
  EXPECT_EQ(oldTileset.at("root").at("content").at("uri"), "0_0_0.glb?v=2");
  EXPECT_EQ(get("/v1/models/m/3dtiles/0_0_0.glb?v=2").status, 200);
}

}  // namespace
}  // namespace vsm::server
