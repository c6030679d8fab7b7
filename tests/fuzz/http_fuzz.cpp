// Fuzz target: an HTTP/1.1 request as bytes off the wire, parsed by Beast with the server's
// limits (as server/http/server.cpp reads requests), then through the Pipeline (bearer token,
// routing, percent-decoding of path parameters, 404/405) to handlers that parse what the real
// routes parse: query parameters, patch keys, the LOD query and the POST bodies.
//
// The routes are those of proto/openapi.yaml (the contract), read at start-up, plus the viewer's
// tail route. The handlers only parse, so a request is answered 2xx or 4xx: a 500 means an
// exception other than a core::Error escaped a parser, and stops the run.
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <regex>
#include <string>
#include <vector>

#include <boost/asio/buffer.hpp>
#include <boost/beast/http/parser.hpp>
#include <boost/beast/http/string_body.hpp>
#include <nlohmann/json.hpp>

#include "core/pyramid/patch_key.hpp"
#include "server/api/requests.hpp"
#include "server/http/pipeline.hpp"
#include "server/http/router.hpp"
#include "tests/fuzz/fuzz_support.hpp"

using namespace vsm;
using namespace vsm::server;
namespace bhttp = boost::beast::http;

namespace {

// server::Limits' defaults.
constexpr std::size_t kBodyLimit = 1024 * 1024;
constexpr std::uint32_t kHeaderLimit = 16 * 1024;

http::Response parseAll(const http::Request& request, const std::string& pattern,
                        const std::vector<std::string>& queryNames) {
  for (const std::string& name : queryNames) {
    request.queryParam(name);
  }
  if (const auto p = request.params.find("p"); p != request.params.end()) {
    core::PatchKey::parse(p->second);
  }
  if (pattern.ends_with("/lod") && request.queryParam("eye")) {
    api::parseCameraQuery(request);
  } else if (pattern.ends_with("/lod")) {
    const auto box = request.queryParam("box");
    const auto resolution = request.queryParam("resolution");
    if (!box || !resolution) {
      throw core::Error(core::ErrorCode::InvalidArgument, "lod needs box and resolution");
    }
    api::parseLodQuery(*box, *resolution);
  }
  if (request.method == http::Method::Post && pattern == "/v1/models") {
    api::parseModelRequest(request);
  }
  if (request.method == http::Method::Post && pattern == "/v1/jobs") {
    api::parseMergeRequest(request);
  }
  return http::jsonResponse(200, {{"route", pattern}});
}

/// The router of every route of proto/openapi.yaml.
struct Api {
  http::Router router;
  std::vector<std::string> queryNames;
  http::Pipeline pipeline{router, "t0k3n"};

  Api() {
    std::ifstream in(VSM_SOURCE_DIR "/proto/openapi.yaml");
    const std::regex pathLine(R"(^  (/\S+):\s*$)");
    const std::regex methodLine(R"(^    (get|post|put|patch|delete):)");
    const std::regex queryName(R"(name: (\w+), in: query)");
    std::vector<std::pair<http::Method, std::string>> routes{
        {http::Method::Get, "/viewer/{path...}"}};
    std::string path;
    for (std::string line; std::getline(in, line);) {
      std::smatch m;
      if (std::regex_search(line, m, pathLine)) {
        path = m[1];
      } else if (!path.empty() && std::regex_search(line, m, methodLine)) {
        std::string method = m[1];
        for (char& c : method) {
          c = static_cast<char>(c - 'a' + 'A');
        }
        routes.emplace_back(http::parseMethod(method), path);
      } else if (std::regex_search(line, m, queryName)) {
        queryNames.push_back(m[1]);
      }
    }
    fuzz::check(routes.size() > 10 && !queryNames.empty(), "proto/openapi.yaml lists the API");
    for (const auto& [method, pattern] : routes) {
      router.add(method, pattern, [this, pattern = pattern](const http::Request& request) {
        return parseAll(request, pattern, queryNames);
      });
    }
  }
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static Api api;
  bhttp::request_parser<bhttp::string_body> parser;
  parser.body_limit(kBodyLimit);
  parser.header_limit(kHeaderLimit);
  parser.eager(true);
  boost::beast::error_code ec;
  std::size_t used = 0;
  while (!parser.is_done() && used < size) {
    const std::size_t n = parser.put(boost::asio::buffer(data + used, size - used), ec);
    if (ec || n == 0) {
      return 0;  // malformed (answered 400 by the server) or incomplete
    }
    used += n;
  }
  if (!parser.is_done()) {
    return 0;
  }
  // As Server's connection turns a Beast message into an http::Request.
  bhttp::request<bhttp::string_body> message = parser.release();
  http::Request request;
  request.methodName = std::string(message.method_string());
  request.method = http::parseMethod(request.methodName);
  request.target = std::string(message.target());
  for (const auto& field : message) {
    std::string name(field.name_string());
    for (char& c : name) {
      c = (c >= 'A' && c <= 'Z') ? static_cast<char>(c + 32) : c;
    }
    request.headers.emplace_back(std::move(name), std::string(field.value()));
  }
  request.body = std::move(message.body());
  request.id = http::requestIdFor(request);

  const http::Handled handled = api.pipeline.handle(request);
  const int status = handled.response.status;
  fuzz::check(status >= 200 && status < 500, "parsing answers 2xx or 4xx, never 5xx");
  return 0;
}
