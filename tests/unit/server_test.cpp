#include <gtest/gtest.h>

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <zlib.h>
#include <nlohmann/json.hpp>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"
#include "core/opc/texture_file.hpp"
#include "server/api/diff_gate.hpp"
#include "server/api/static_routes.hpp"
#include "server/api/system_routes.hpp"
#include "server/app/application.hpp"
#include "server/cluster/etcd_client.hpp"
#include "server/config/config.hpp"
#include "server/exec/work_pool.hpp"
#include "server/http/gzip.hpp"
#include "server/http/message.hpp"
#include "server/http/pipeline.hpp"
#include "server/http/router.hpp"
#include "server/http/server.hpp"
#include "server/metrics/metrics.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::server {
namespace {

using core::Error;
using core::ErrorCode;
using namespace std::chrono_literals;
using nlohmann::json;

constexpr std::size_t kKiB = 1024;
constexpr std::size_t kMiB = 1024 * kKiB;
constexpr std::size_t kGiB = 1024 * kMiB;

using core::test::errorOf;
using core::test::TempFile;

// --- gzip -----------------------------------------------------------------------------------

http::Request withAcceptEncoding(std::string value) {
  http::Request request;
  request.headers.emplace_back("accept-encoding", std::move(value));
  return request;
}

/// Inflates one gzip member with zlib's inflate (the decoder, not the encoder under test).
std::string gunzip(const std::string& data) {
  z_stream stream{};
  EXPECT_EQ(inflateInit2(&stream, 15 + 16), Z_OK);
  std::string out;
  char buffer[4096];
  stream.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(data.data()));
  stream.avail_in = static_cast<uInt>(data.size());
  int result = Z_OK;
  while (result == Z_OK) {
    stream.next_out = reinterpret_cast<Bytef*>(buffer);
    stream.avail_out = sizeof buffer;
    result = inflate(&stream, Z_NO_FLUSH);
    out.append(buffer, sizeof buffer - stream.avail_out);
  }
  EXPECT_EQ(result, Z_STREAM_END);
  EXPECT_EQ(stream.avail_in, 0U) << "bytes after the gzip member";
  inflateEnd(&stream);
  return out;
}

TEST(Gzip, AcceptEncodingNegotiation) {
  EXPECT_FALSE(http::acceptsGzip(http::Request{}));
  EXPECT_TRUE(http::acceptsGzip(withAcceptEncoding("gzip")));
  EXPECT_TRUE(http::acceptsGzip(withAcceptEncoding("gzip, deflate, br")));
  EXPECT_TRUE(http::acceptsGzip(withAcceptEncoding("br;q=1.0, GZIP;q=0.5")));
  EXPECT_TRUE(http::acceptsGzip(withAcceptEncoding("x-gzip")));
  EXPECT_TRUE(http::acceptsGzip(withAcceptEncoding("*")));
  EXPECT_TRUE(http::acceptsGzip(withAcceptEncoding("identity, *;q=0.1")));
  EXPECT_FALSE(http::acceptsGzip(withAcceptEncoding("identity")));
  EXPECT_FALSE(http::acceptsGzip(withAcceptEncoding("br, deflate")));
  EXPECT_FALSE(http::acceptsGzip(withAcceptEncoding("gzip;q=0")));
  EXPECT_FALSE(http::acceptsGzip(withAcceptEncoding("gzip;q=0.000")));
  // Named explicitly, gzip's own q wins over the wildcard's.
  EXPECT_FALSE(http::acceptsGzip(withAcceptEncoding("gzip;q=0, *")));
  EXPECT_TRUE(http::acceptsGzip(withAcceptEncoding("*;q=0, gzip")));
  // A malformed q-value refuses rather than guessing.
  EXPECT_FALSE(http::acceptsGzip(withAcceptEncoding("gzip;q=high")));
  EXPECT_FALSE(http::acceptsGzip(withAcceptEncoding("gzip;q=2")));
  EXPECT_FALSE(http::acceptsGzip(withAcceptEncoding("gzipped")));
}

TEST(Gzip, RoundTripsThroughInflate) {
  std::string json = "{\"tiles\":[";
  for (int i = 0; i < 5000; ++i) {
    json += "{\"uri\":\"3_" + std::to_string(i) + "_1.glb\"},";
  }
  json += "]}";
  for (const int level : {1, 6, 9}) {
    const std::string packed = http::gzip(json, level);
    ASSERT_GE(packed.size(), 18U);
    EXPECT_EQ(static_cast<unsigned char>(packed[0]), 0x1f);  // RFC 1952 magic
    EXPECT_EQ(static_cast<unsigned char>(packed[1]), 0x8b);
    EXPECT_LT(packed.size(), json.size() / 4) << "level " << level;
    EXPECT_EQ(gunzip(packed), json);
  }
  EXPECT_EQ(gunzip(http::gzip("")), "");
  // Incompressible bytes still round-trip (the output may be larger than the input).
  std::string noise(100000, '\0');
  std::uint32_t x = 12345;
  for (char& c : noise) {
    x = x * 1664525U + 1013904223U;
    c = static_cast<char>(x >> 24);
  }
  EXPECT_EQ(gunzip(http::gzip(noise)), noise);
}

TEST(Gzip, ResponseHeaders) {
  http::Response response;
  http::setGzipEncoded(response);
  ASSERT_NE(response.header("content-encoding"), nullptr);
  EXPECT_EQ(*response.header("Content-Encoding"), "gzip");
  ASSERT_NE(response.header("vary"), nullptr);
  EXPECT_EQ(*response.header("Vary"), "Accept-Encoding");
}

TEST(Base64, MatchesTheVectorsOfRfc4648AndRefusesJunk) {
  const std::pair<std::string, std::string> vectors[] = {{"", ""},
                                                         {"f", "Zg=="},
                                                         {"fo", "Zm8="},
                                                         {"foo", "Zm9v"},
                                                         {"foob", "Zm9vYg=="},
                                                         {"fooba", "Zm9vYmE="},
                                                         {"foobar", "Zm9vYmFy"}};
  for (const auto& [plain, encoded] : vectors) {
    EXPECT_EQ(cluster::base64Encode(plain), encoded);
    EXPECT_EQ(cluster::base64Decode(encoded), plain);
  }
  const std::string bytes{'\0', '\xff', '\x80', '/', '+'};
  EXPECT_EQ(cluster::base64Decode(cluster::base64Encode(bytes)), bytes);
  for (const char* junk : {"Zg=", "Z===", "Zg=a", "Zm9v!A==", "=Zm9"}) {
    EXPECT_THROW(cluster::base64Decode(junk), core::Error) << junk;
  }
}

// --- router ---------------------------------------------------------------------------------

http::Handler named(std::string name) {
  return [name](const http::Request&) {
    http::Response r;
    r.body = name;
    return r;
  };
}

http::Router sampleRouter() {
  http::Router router;
  router.add(http::Method::Get, "/v1/models", named("list"));
  router.add(http::Method::Post, "/v1/models", named("open"));
  router.add(http::Method::Get, "/v1/models/{m}", named("model"));
  router.add(http::Method::Delete, "/v1/models/{m}", named("close"));
  router.add(http::Method::Get, "/v1/models/stats", named("literal"));
  router.add(http::Method::Get, "/v1/models/{m}/patches/{p}", named("patch"));
  router.add(http::Method::Get, "/v1/models/{m}/3dtiles/tileset.json", named("tileset"));
  router.add(http::Method::Get, "/v1/models/{m}/3dtiles/{p}.glb", named("glb"));
  router.add(http::Method::Get, "/v1/models/{m}/3dtiles/{p}", named("bare"));
  return router;
}

std::string routed(const http::Router& router, http::Method method, std::string_view path) {
  const http::RouteMatch match = router.match(method, path);
  return match.route != nullptr ? match.route->handler(http::Request{}).body : "-";
}

TEST(Router, MatchesLiteralsAndDecodesParameters) {
  const http::Router router = sampleRouter();
  EXPECT_EQ(routed(router, http::Method::Get, "/v1/models"), "list");
  EXPECT_EQ(routed(router, http::Method::Post, "/v1/models"), "open");
  const auto match = router.match(http::Method::Get, "/v1/models/a%20b/patches/3_1_2");
  ASSERT_EQ(match.kind, http::RouteMatch::Kind::Found);
  EXPECT_EQ(match.route->pattern, "/v1/models/{m}/patches/{p}");
  EXPECT_EQ(match.params.at("m"), "a b");
  EXPECT_EQ(match.params.at("p"), "3_1_2");
}

TEST(Router, AnEncodedSlashStaysInsideItsSegment) {
  const http::Router router = sampleRouter();
  const auto match = router.match(http::Method::Get, "/v1/models/a%2Fb");
  ASSERT_EQ(match.kind, http::RouteMatch::Kind::Found);
  EXPECT_EQ(match.params.at("m"), "a/b");
}

TEST(Router, TheMostSpecificPatternWins) {
  const http::Router router = sampleRouter();
  EXPECT_EQ(routed(router, http::Method::Get, "/v1/models/stats"), "literal");
  EXPECT_EQ(routed(router, http::Method::Get, "/v1/models/other"), "model");
  EXPECT_EQ(routed(router, http::Method::Get, "/v1/models/m/3dtiles/tileset.json"), "tileset");
  EXPECT_EQ(routed(router, http::Method::Get, "/v1/models/m/3dtiles/0_0_0.glb"), "glb");
  EXPECT_EQ(routed(router, http::Method::Get, "/v1/models/m/3dtiles/0_0_0"), "bare");
  EXPECT_EQ(sampleRouter().match(http::Method::Get, "/v1/models/m/3dtiles/7.glb").params.at("p"),
            "7");
}

TEST(Router, UnknownPathsAreNotFound) {
  const http::Router router = sampleRouter();
  for (const char* path : {"/", "/v1", "/v1/models/", "/v1//models", "/v1/models/m/patches",
                           "/v1/models/%zz", "v1/models", ""}) {
    EXPECT_EQ(router.match(http::Method::Get, path).kind, http::RouteMatch::Kind::NotFound) << path;
  }
  // ".glb" alone leaves the parameter empty: no match for the affixed pattern.
  EXPECT_EQ(routed(router, http::Method::Get, "/v1/models/m/3dtiles/.glb"), "bare");
}

TEST(Router, AWrongMethodListsTheAllowedOnes) {
  const http::Router router = sampleRouter();
  auto match = router.match(http::Method::Put, "/v1/models");
  EXPECT_EQ(match.kind, http::RouteMatch::Kind::MethodNotAllowed);
  EXPECT_EQ(match.allowed, (std::vector<http::Method>{http::Method::Get, http::Method::Head,
                                                      http::Method::Post, http::Method::Options}));
  match = router.match(http::Method::Delete, "/v1/models/m/patches/p");
  EXPECT_EQ(match.kind, http::RouteMatch::Kind::MethodNotAllowed);
}

TEST(Router, HeadIsRoutedToGet) {
  const http::Router router = sampleRouter();
  const auto match = router.match(http::Method::Head, "/v1/models");
  ASSERT_EQ(match.kind, http::RouteMatch::Kind::Found);
  EXPECT_EQ(match.route->method, http::Method::Get);
}

TEST(Router, RejectsMalformedAndDuplicatePatterns) {
  http::Router router;
  router.add(http::Method::Get, "/a/{x}", named("x"));
  for (const char* pattern :
       {"a", "/a//b", "/a/{", "/a/}", "/a/{}", "/a/{x-y}", "/a/{x}{y}", "/a/{x}/{x}"}) {
    EXPECT_EQ(errorOf([&] { router.add(http::Method::Get, pattern, named("")); }).first,
              ErrorCode::InvalidArgument)
        << pattern;
  }
  EXPECT_EQ(errorOf([&] { router.add(http::Method::Get, "/a/{x}", named("")); }).first,
            ErrorCode::InvalidArgument);
  EXPECT_EQ(errorOf([&] { router.add(http::Method::Head, "/b", named("")); }).first,
            ErrorCode::InvalidArgument);
  EXPECT_EQ(router.size(), 1u);
}

// --- pipeline -------------------------------------------------------------------------------

http::Request request(http::Method method, std::string target) {
  http::Request r;
  r.method = method;
  r.methodName = std::string(http::toString(method));
  r.target = std::move(target);
  r.id = "req-1";
  return r;
}

json errorBody(const http::Response& response) {
  const json body = json::parse(response.body);
  EXPECT_EQ(body.size(), 1u);
  EXPECT_EQ(body.at("error").size(), 2u);
  EXPECT_TRUE(body.at("error").at("code").is_string());
  EXPECT_TRUE(body.at("error").at("message").is_string());
  return body.at("error");
}

TEST(ErrorTable, MapsEveryCodeToOneStatus) {
  EXPECT_EQ(http::statusFor(ErrorCode::InvalidArgument).status, 400);
  EXPECT_EQ(http::statusFor(ErrorCode::NotFound).status, 404);
  EXPECT_EQ(http::statusFor(ErrorCode::Conflict).status, 409);
  EXPECT_EQ(http::statusFor(ErrorCode::Cancelled).status, 409);
  EXPECT_EQ(http::statusFor(ErrorCode::Unavailable).status, 503);
  EXPECT_TRUE(http::statusFor(ErrorCode::Unavailable).retryAfter);
  EXPECT_EQ(http::statusFor(ErrorCode::ResourceExhausted).status, 503);
  EXPECT_TRUE(http::statusFor(ErrorCode::ResourceExhausted).retryAfter);
  for (const auto code : {ErrorCode::Corrupt, ErrorCode::Io, ErrorCode::Internal}) {
    EXPECT_EQ(http::statusFor(code).status, 500);
    EXPECT_TRUE(http::statusFor(code).internal);
  }
}

/// A router whose one route throws what the test puts in `thrown`.
struct ThrowingRoute {
  std::function<void()> thrown;
  http::Router router;
  ThrowingRoute() {
    router.add(http::Method::Get, "/x", [this](const http::Request&) -> http::Response {
      thrown();
      return {};
    });
    router.add(http::Method::Post, "/x", named("posted"));
  }
};

TEST(Pipeline, TurnsCoreErrorsIntoJsonErrors) {
  ThrowingRoute route;
  const http::Pipeline pipeline(route.router, "");
  route.thrown = [] { throw Error(ErrorCode::NotFound, "no model 'm'"); };
  auto r = request(http::Method::Get, "/x");
  http::Handled handled = pipeline.handle(r);
  EXPECT_EQ(handled.response.status, 404);
  EXPECT_EQ(handled.route, "/x");
  EXPECT_EQ(errorBody(handled.response).at("code"), "not_found");
  EXPECT_EQ(errorBody(handled.response).at("message"), "no model 'm'");

  route.thrown = [] { throw Error(ErrorCode::ResourceExhausted, "budget full"); };
  handled = pipeline.handle(r);
  EXPECT_EQ(handled.response.status, 503);
  ASSERT_NE(handled.response.header("Retry-After"), nullptr);
  EXPECT_EQ(*handled.response.header("retry-after"), "1");
}

TEST(Pipeline, InternalErrorsHideTheirMessageAndNameTheRequestId) {
  ThrowingRoute route;
  const http::Pipeline pipeline(route.router, "");
  auto r = request(http::Method::Get, "/x");
  const core::log::Level saved = core::log::level();
  core::log::setLevel(core::log::Level::Off);  // the test provokes error lines on purpose
  for (const auto& thrown : std::vector<std::function<void()>>{
           [] { throw Error(ErrorCode::Io, "cannot read '/srv/secret/path'"); },
           [] { throw std::runtime_error("/srv/secret/path"); }, [] { throw 42; }}) {
    route.thrown = thrown;
    const http::Handled handled = pipeline.handle(r);
    EXPECT_EQ(handled.response.status, 500);
    const std::string message = errorBody(handled.response).at("message");
    EXPECT_EQ(message.find("secret"), std::string::npos);
    EXPECT_NE(message.find("req-1"), std::string::npos);
  }
  core::log::setLevel(saved);
}

TEST(Pipeline, WritesNeedTheBearerTokenReadsDoNot) {
  ThrowingRoute route;
  route.thrown = [] {};
  const http::Pipeline pipeline(route.router, "s3cret");

  auto post = request(http::Method::Post, "/x");
  http::Handled handled = pipeline.handle(post);
  EXPECT_EQ(handled.response.status, 401);
  EXPECT_EQ(errorBody(handled.response).at("code"), "unauthorized");
  ASSERT_NE(handled.response.header("WWW-Authenticate"), nullptr);

  post.headers = {{"authorization", "Bearer wrong"}};
  handled = pipeline.handle(post);
  EXPECT_EQ(handled.response.status, 401);
  EXPECT_NE(handled.response.header("WWW-Authenticate")->find("invalid_token"), std::string::npos);

  post.headers = {{"authorization", "Bearer s3cret"}};
  handled = pipeline.handle(post);
  EXPECT_EQ(handled.response.status, 200);
  EXPECT_EQ(handled.response.body, "posted");

  // Writes to unknown paths are refused before routing: no probing without the token.
  auto probe = request(http::Method::Delete, "/nothing");
  EXPECT_EQ(pipeline.handle(probe).response.status, 401);

  auto get = request(http::Method::Get, "/x");
  EXPECT_EQ(pipeline.handle(get).response.status, 200);
}

TEST(Pipeline, AuthorizeDecidesOnTheHeaderAlone) {
  ThrowingRoute route;
  route.thrown = [] {};
  const http::Pipeline pipeline(route.router, "s3cret");
  auto post = request(http::Method::Post, "/x");
  post.body = "never looked at";
  const auto refused = pipeline.authorize(post);
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->response.status, 401);
  EXPECT_EQ(refused->route, "unauthorized");
  EXPECT_NE(refused->response.header("X-Request-Id"), nullptr);  // finished like any response
  // Prefixes, extensions, other lengths and overlong credentials are all refused.
  for (const std::string& credentials : std::vector<std::string>{
           "s3cre", "s3cret2", "s3cretx", std::string(5000, 's'), std::string("s3cret\0", 7), ""}) {
    post.headers = {{"authorization", "Bearer " + credentials}};
    EXPECT_TRUE(pipeline.authorize(post)) << credentials.substr(0, 10);
  }
  post.headers = {{"authorization", "bearer s3cret"}};
  EXPECT_FALSE(pipeline.authorize(post));
  post.headers = {{"authorization", "Basic s3cret"}};
  EXPECT_TRUE(pipeline.authorize(post));
  auto get = request(http::Method::Get, "/x");
  EXPECT_FALSE(pipeline.authorize(get));  // reads are public
  const http::Pipeline open(route.router, "");
  EXPECT_FALSE(open.authorize(post));  // no token: writes are open
}

TEST(Pipeline, AnswersNotFoundMethodNotAllowedAndPreflight) {
  const http::Router router = sampleRouter();
  const http::Pipeline pipeline(router, "");
  auto r = request(http::Method::Get, "/v2/nothing?x=1");
  http::Handled handled = pipeline.handle(r);
  EXPECT_EQ(handled.response.status, 404);
  EXPECT_EQ(errorBody(handled.response).at("code"), "not_found");
  EXPECT_EQ(handled.route, "unmatched");

  r = request(http::Method::Put, "/v1/models");
  handled = pipeline.handle(r);
  EXPECT_EQ(handled.response.status, 405);
  EXPECT_EQ(errorBody(handled.response).at("code"), "method_not_allowed");
  EXPECT_EQ(*handled.response.header("Allow"), "GET, HEAD, POST, OPTIONS");

  r = request(http::Method::Options, "/v1/models/m");
  r.headers = {{"origin", "https://viewer.example"}, {"access-control-request-method", "DELETE"}};
  handled = pipeline.handle(r);
  EXPECT_EQ(handled.response.status, 204);
  EXPECT_EQ(*handled.response.header("Access-Control-Allow-Methods"), "GET, HEAD, DELETE, OPTIONS");
  EXPECT_NE(handled.response.header("Access-Control-Allow-Headers")->find("Authorization"),
            std::string::npos);
}

TEST(Pipeline, EveryResponseCarriesCorsTheRequestIdAndACachePolicy) {
  const http::Router router = sampleRouter();
  const http::Pipeline pipeline(router, "");
  for (const char* target : {"/v1/models", "/missing"}) {
    auto r = request(http::Method::Get, target);
    const http::Handled handled = pipeline.handle(r);
    EXPECT_EQ(*handled.response.header("Access-Control-Allow-Origin"), "*");
    EXPECT_EQ(*handled.response.header("X-Request-Id"), "req-1");
    EXPECT_EQ(*handled.response.header("Cache-Control"), "no-store");
  }
}

// --- messages -------------------------------------------------------------------------------

TEST(Etag, IfNoneMatchComparesWeaklyAndHandlesListsAndStar) {
  const std::string etag = http::strongEtag("m-0_0_0-v3");
  auto r = request(http::Method::Get, "/");
  EXPECT_FALSE(http::ifNoneMatch(r, etag));
  for (const char* header : {R"("m-0_0_0-v3")", R"(W/"m-0_0_0-v3")", R"("a", "m-0_0_0-v3")",
                             R"("a,b" , W/"m-0_0_0-v3")", "*"}) {
    r.headers = {{"if-none-match", header}};
    EXPECT_TRUE(http::ifNoneMatch(r, etag)) << header;
  }
  for (const char* header : {R"("m-0_0_0-v2")", "m-0_0_0-v3", R"("m-0_0_0-v3)", ""}) {
    r.headers = {{"if-none-match", header}};
    EXPECT_FALSE(http::ifNoneMatch(r, etag)) << header;
  }
  const http::Response notModified = http::notModified(etag, http::cache_control::kRevalidate);
  EXPECT_EQ(notModified.status, 304);
  EXPECT_TRUE(notModified.body.empty());
  EXPECT_EQ(*notModified.header("ETag"), etag);
  EXPECT_EQ(*notModified.header("Cache-Control"), "no-cache");
}

TEST(Request, SplitsTheTargetAndDecodesQueryParameters) {
  auto r = request(http::Method::Get, "/v1/models/m/lod?box=0,0,0,1,1,1&resolution=0.5&q=a+b%21&e");
  EXPECT_EQ(r.path(), "/v1/models/m/lod");
  EXPECT_EQ(r.queryParam("box"), "0,0,0,1,1,1");
  EXPECT_EQ(r.queryParam("resolution"), "0.5");
  EXPECT_EQ(r.queryParam("q"), "a b!");
  EXPECT_EQ(r.queryParam("e"), "");
  EXPECT_EQ(r.queryParam("missing"), std::nullopt);
  r.target = "/x?bad=%g0";
  EXPECT_EQ(errorOf([&] { r.queryParam("bad"); }).first, ErrorCode::InvalidArgument);
  EXPECT_EQ(errorOf([&] { r.param("m"); }).first, ErrorCode::Internal);
}

TEST(Request, KeepsASaneClientRequestIdAndReplacesOthers) {
  auto r = request(http::Method::Get, "/");
  r.headers = {{"x-request-id", "abc-123_x.y"}};
  EXPECT_EQ(http::requestIdFor(r), "abc-123_x.y");
  r.headers = {{"x-request-id", "bad id\r\n"}};
  const std::string fresh = http::requestIdFor(r);
  EXPECT_EQ(fresh.size(), 16u);
  EXPECT_NE(fresh, http::newRequestId());
}

TEST(Request, JsonBodyNeedsJson) {
  auto r = request(http::Method::Post, "/");
  r.body = R"({"id": "m"})";
  EXPECT_EQ(http::jsonBody(r).at("id"), "m");
  r.headers = {{"content-type", "application/json; charset=utf-8"}};
  EXPECT_EQ(http::jsonBody(r).at("id"), "m");
  r.headers = {{"content-type", "text/plain"}};
  EXPECT_EQ(errorOf([&] { http::jsonBody(r); }).first, ErrorCode::InvalidArgument);
  r.headers.clear();
  r.body = "{";
  EXPECT_EQ(errorOf([&] { http::jsonBody(r); }).first, ErrorCode::InvalidArgument);
}

TEST(Request, JsonBodyNestsAtMostMaxDepthLevels) {
  auto r = request(http::Method::Post, "/");
  const auto nested = [](int depth) {
    std::string text;
    for (int i = 0; i < depth; ++i) {
      text += i % 2 == 0 ? "[" : "{\"a\":";
    }
    text += "0";
    for (int i = depth - 1; i >= 0; --i) {
      text += i % 2 == 0 ? "]" : "}";
    }
    return text;
  };
  r.body = nested(http::kMaxJsonDepth);
  EXPECT_TRUE(http::jsonBody(r).is_array());
  r.body = nested(http::kMaxJsonDepth + 1);
  EXPECT_EQ(errorOf([&] { http::jsonBody(r); }),
            std::pair(ErrorCode::InvalidArgument,
                      std::string("request body nests deeper than 64 levels")));
  // A megabyte of '[' (what the body limit lets through) fails the same way, without recursing.
  r.body = std::string(1 << 20, '[');
  EXPECT_EQ(errorOf([&] { http::jsonBody(r); }).first, ErrorCode::InvalidArgument);
}

// --- metrics --------------------------------------------------------------------------------

TEST(Metrics, RendersCountersHistogramsAndCollectorsInTextFormat) {
  metrics::Registry registry;
  metrics::Counter& requests =
      registry.counter("vsm_test_requests_total", "Requests", {"route", "status"});
  metrics::Histogram& latency =
      registry.histogram("vsm_test_seconds", "Latency", {"route"}, {0.001, 0.1});
  registry.counter("vsm_test_idle_total", "Never incremented");
  registry.collector([] {
    return std::vector<metrics::Snapshot>{
        {"vsm_test_open", "Open now", metrics::Type::Gauge, {"name"}, {{{"a\"b\\c"}, 2.5}}}};
  });
  requests.inc({"/x", "200"});
  requests.inc({"/x", "200"}, 2);
  latency.observe({"/x"}, 0.0005);
  latency.observe({"/x"}, 0.05);
  latency.observe({"/x"}, 7);

  const std::string text = registry.render();
  EXPECT_NE(text.find("# TYPE vsm_test_requests_total counter\n"), std::string::npos);
  EXPECT_NE(text.find("vsm_test_requests_total{route=\"/x\",status=\"200\"} 3\n"),
            std::string::npos);
  EXPECT_NE(text.find("vsm_test_idle_total 0\n"), std::string::npos);
  EXPECT_NE(text.find("# TYPE vsm_test_seconds histogram\n"), std::string::npos);
  EXPECT_NE(text.find("vsm_test_seconds_bucket{route=\"/x\",le=\"0.001\"} 1\n"), std::string::npos);
  EXPECT_NE(text.find("vsm_test_seconds_bucket{route=\"/x\",le=\"0.1\"} 2\n"), std::string::npos);
  EXPECT_NE(text.find("vsm_test_seconds_bucket{route=\"/x\",le=\"+Inf\"} 3\n"), std::string::npos);
  EXPECT_NE(text.find("vsm_test_seconds_count{route=\"/x\"} 3\n"), std::string::npos);
  EXPECT_NE(text.find("vsm_test_seconds_sum{route=\"/x\"} 7.0505\n"), std::string::npos);
  EXPECT_NE(text.find("vsm_test_open{name=\"a\\\"b\\\\c\"} 2.5\n"), std::string::npos);
  EXPECT_EQ(requests.value({"/x", "200"}), 3.0);
}

TEST(Metrics, RejectsBadNamesDuplicatesAndWrongLabelCounts) {
  metrics::Registry registry;
  metrics::Counter& counter = registry.counter("ok_total", "", {"a"});
  EXPECT_EQ(errorOf([&] { registry.counter("ok_total", ""); }).first, ErrorCode::InvalidArgument);
  EXPECT_EQ(errorOf([&] { registry.counter("1bad", ""); }).first, ErrorCode::InvalidArgument);
  EXPECT_EQ(errorOf([&] { registry.counter("x", "", {"le"}); }).first, ErrorCode::InvalidArgument);
  EXPECT_EQ(errorOf([&] {
              registry.histogram("h", "", {}, {1, 0.5});
            }).first,
            ErrorCode::InvalidArgument);
  EXPECT_EQ(errorOf([&] { counter.inc({"a", "b"}); }).first, ErrorCode::Internal);
}

// --- descriptor plan --------------------------------------------------------------------------

// vsmd.descriptors runs the daemon at 1024; these are the plans at and around the bounds.
TEST(DescriptorPlan, SharesTheLimitWithoutEverExceedingIt) {
  // A service's default soft limit with the default 512 connections, 6 threads (2 of them job
  // threads) and 16 models: 158 kept for the process (64 + 2 x 6 + 64 being refused + a writer
  // lock per model + an edit's directory per job thread), 512 connections, the rest for cached
  // files.
  const DescriptorPlan plan = planDescriptors(1024, 512, 6, 16, 2);
  EXPECT_EQ(plan.connections, 512u);
  EXPECT_EQ(plan.cachedFiles, 1024u - 158 - 512);
  // Every model and job thread allowed takes its descriptor from the cache's share.
  EXPECT_EQ(planDescriptors(1024, 512, 6, 116, 2).cachedFiles, 1024u - 258 - 512);
  EXPECT_EQ(planDescriptors(1024, 512, 6, 16, 10).cachedFiles, 1024u - 166 - 512);
  // A generous hard limit: the cache's share stops at 65536.
  EXPECT_EQ(planDescriptors(1u << 20, 512, 6, 16, 2).cachedFiles, 65536u);
  EXPECT_EQ(planDescriptors(1u << 20, 512, 6, 16, 2).connections, 512u);
  // Too few for both: connections give way so that 64 files can still be cached.
  const DescriptorPlan tight = planDescriptors(512, 512, 6, 16, 2);
  EXPECT_EQ(tight.cachedFiles, 64u);
  EXPECT_EQ(tight.connections, 512u - 158 - 64);
  for (std::size_t limit = 300; limit <= 70000; limit += 37) {
    for (const std::size_t connections : {1u, 64u, 512u, 4096u}) {
      const DescriptorPlan p = planDescriptors(limit, connections, 6, 16, 2);
      EXPECT_LE(p.connections + p.cachedFiles + 158, limit) << limit << " " << connections;
      EXPECT_LE(p.connections, connections);
      EXPECT_GE(p.cachedFiles, 8u);
      EXPECT_GE(p.connections, std::min<std::size_t>(connections, 8));
    }
  }
  // Below what the process needs for itself the plan still leaves something to run with.
  const DescriptorPlan starved = planDescriptors(100, 512, 6, 16, 2);
  EXPECT_GE(starved.connections, 8u);
  EXPECT_GE(starved.cachedFiles, 8u);
}

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
                                                                      {"heights", 0}}));
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

TEST(Router, ATailParameterTakesTheRestOfThePath) {
  http::Router router;
  router.add(http::Method::Get, "/viewer/{path...}", named("static"));
  router.add(http::Method::Get, "/viewer/api", named("literal"));
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"/viewer/", ""},
      {"/viewer", ""},
      {"/viewer/index.html", "index.html"},
      {"/viewer/vendor/three/three.module.js", "vendor/three/three.module.js"},
      {"/viewer/a//b/", "a//b/"},
      {"/viewer/a%2F..%2Fb", "a/../b"}};
  for (const auto& [path, rest] : cases) {
    const auto match = router.match(http::Method::Get, path);
    ASSERT_EQ(match.kind, http::RouteMatch::Kind::Found) << path;
    EXPECT_EQ(match.route->pattern, "/viewer/{path...}") << path;
    EXPECT_EQ(match.params.at("path"), rest) << path;
  }
  EXPECT_EQ(router.match(http::Method::Get, "/viewer/api").route->pattern, "/viewer/api");
  EXPECT_EQ(router.match(http::Method::Get, "/other/x").kind, http::RouteMatch::Kind::NotFound);
  for (const char* pattern : {"/a/{x...}/b", "/a/p{x...}", "/a/{x...}.js", "/a/{...}"}) {
    EXPECT_EQ(errorOf([&] { router.add(http::Method::Get, pattern, named("")); }).first,
              ErrorCode::InvalidArgument)
        << pattern;
  }
}

/// A viewer directory with an index, a nested module, a hidden file, a link inside the tree and
/// links out of it, next to a secret that must never be served.
class StaticFiles : public ::testing::Test {
 protected:
  void SetUp() override {
    base_ = std::filesystem::temp_directory_path() /
            ("vsm-static-" + std::to_string(::getpid()) + "-" +
             ::testing::UnitTest::GetInstance()->current_test_info()->name());
    std::filesystem::remove_all(base_);
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
  void TearDown() override { std::filesystem::remove_all(base_); }

  static void write(const std::filesystem::path& path, const std::string& text) {
    std::ofstream(path, std::ios::binary) << text;
  }

  std::filesystem::path base_;
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

// --- the HTTP server on a real socket -------------------------------------------------------

/// A descriptor closed on destruction (what keeps a response's body file open).
struct OpenFd {
  int fd = -1;
  ~OpenFd() { ::close(fd); }
};

/// A blocking client of one keep-alive connection to 127.0.0.1:port.
class RawClient {
 public:
  explicit RawClient(std::uint16_t port) : fd_(::socket(AF_INET, SOCK_STREAM, 0)) {
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_port = htons(port);
    address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    timeval timeout{5, 0};
    ::setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &timeout, sizeof timeout);
    connected_ = ::connect(fd_, reinterpret_cast<sockaddr*>(&address), sizeof address) == 0;
  }
  ~RawClient() { ::close(fd_); }
  bool connected() const { return connected_; }

  /// Sends a GET and returns the response's body; "" when the connection ended first.
  std::string get(const std::string& path) {
    const std::string request = "GET " + path + " HTTP/1.1\r\nHost: test\r\n\r\n";
    if (::send(fd_, request.data(), request.size(), MSG_NOSIGNAL) !=
        static_cast<ssize_t>(request.size())) {
      return "";
    }
    std::size_t headerEnd = std::string::npos;
    while ((headerEnd = buffer_.find("\r\n\r\n")) == std::string::npos) {
      if (!readMore()) {
        return "";
      }
    }
    const std::size_t at = buffer_.find("Content-Length: ");
    const std::size_t length = std::stoul(buffer_.substr(at + 16));
    while (buffer_.size() < headerEnd + 4 + length) {
      if (!readMore()) {
        return "";
      }
    }
    std::string body = buffer_.substr(headerEnd + 4, length);
    buffer_.erase(0, headerEnd + 4 + length);
    return body;
  }

 private:
  bool readMore() {
    char chunk[4096];
    const ssize_t n = ::recv(fd_, chunk, sizeof chunk, 0);
    if (n <= 0) {
      return false;
    }
    buffer_.append(chunk, static_cast<std::size_t>(n));
    return true;
  }

  int fd_;
  bool connected_ = false;
  std::string buffer_;
};

TEST(HttpServer, AFileBodysWriteTimerNeverClosesTheConnectionAfterTheWriteCompleted) {
  // A body file sent by sendfile(2) whose write timer expires (at once: a write timeout of 0) just
  // as the write completes: its handler is queued already and cannot be cancelled any more. It
  // must not close the connection the next request then uses.
  const TempFile body("file body sent by sendfile");
  http::Router router;
  router.add(http::Method::Get, "/file", [&body](const http::Request&) {
    auto owner = std::make_shared<OpenFd>();
    owner->fd = ::open(body.path().c_str(), O_RDONLY | O_CLOEXEC);
    http::Response response;
    response.contentType = "text/plain";
    response.file = {owner->fd, 5, 4};  // "body"
    response.bodyOwner = std::move(owner);
    return response;
  });
  const http::Pipeline pipeline(router, "");
  exec::WorkPool pool("cpu", 2);
  metrics::Registry registry;
  http::ServerOptions options;
  options.ioThreads = 2;
  options.writeTimeout = 0ms;
  http::Server server(options, pipeline, pool, registry);
  server.start();
  RawClient client(server.port());
  ASSERT_TRUE(client.connected());
  for (int i = 0; i < 300; ++i) {
    ASSERT_EQ(client.get("/file"), "body") << "request " << i << " on one connection";
  }
  server.stop(1s);
  pool.join();
}

}  // namespace
}  // namespace vsm::server
