// server/http: gzip, the router, the pipeline (errors, authorization, CORS), messages and
// requests, and the HTTP server on a real socket.
#include <gtest/gtest.h>

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <functional>
#include <stdexcept>
#include <string>
#include <vector>

#include <zlib.h>
#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "server/exec/work_pool.hpp"
#include "server/http/gzip.hpp"
#include "server/http/message.hpp"
#include "server/http/pipeline.hpp"
#include "server/http/router.hpp"
#include "server/http/server.hpp"
#include "server/metrics/metrics.hpp"
#include "tests/unit/server_test_support.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::server {
namespace {

using core::Error;
using core::ErrorCode;
using core::test::errorOf;
using core::test::TempFile;
using namespace std::chrono_literals;
using nlohmann::json;
using test::request;

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
