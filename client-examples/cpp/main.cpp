// vsm_client_example: a small client of vsmd on Boost.Beast. Lists the open models, then downloads
// one patch's positions and decodes the .aara header (proto/openapi.yaml, ../shared/docs/OPC.md).
//
//   vsm_client_example [--host HOST] [--port PORT] [MODEL [PATCH]]
//
// MODEL defaults to the first model listed, PATCH to the root "0_0_0". Synchronous and on one
// keep-alive connection: every request reuses it. Exit 0 on success, 1 on any error (printed).
#include <cmath>
#include <cstdint>
#include <cstring>
#include <iostream>
#include <stdexcept>
#include <string>
#include <vector>

#include <boost/asio/connect.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/beast/core/flat_buffer.hpp>
#include <boost/beast/core/tcp_stream.hpp>
#include <boost/beast/http.hpp>
#include <nlohmann/json.hpp>

namespace beast = boost::beast;
namespace http = beast::http;
namespace net = boost::asio;
using tcp = net::ip::tcp;

namespace {

/// One connection to vsmd; get() sends a GET and reads the whole response.
class VsmConnection {
 public:
  VsmConnection(std::string host, std::string port) : host_(std::move(host)), stream_(ioc_) {
    tcp::resolver resolver(ioc_);
    stream_.expires_after(std::chrono::seconds(10));
    stream_.connect(resolver.resolve(host_, port));
  }

  ~VsmConnection() {
    beast::error_code ignored;
    stream_.socket().shutdown(tcp::socket::shutdown_both, ignored);
  }

  /// The response to GET `target`; a body of up to 64 MiB.
  http::response<http::string_body> get(const std::string& target) {
    http::request<http::empty_body> request{http::verb::get, target, 11};
    request.set(http::field::host, host_);
    request.set(http::field::user_agent, "vsm_client_example");
    request.keep_alive(true);
    stream_.expires_after(std::chrono::seconds(30));
    http::write(stream_, request);
    http::response_parser<http::string_body> parser;
    parser.body_limit(64 * 1024 * 1024);
    http::read(stream_, buffer_, parser);
    return parser.release();
  }

  /// GET `target` as JSON; throws with vsmd's error message on a status other than 200.
  nlohmann::json getJson(const std::string& target) {
    auto response = get(target);
    if (response.result_int() != 200) {
      // vsmd answers errors as {"error": {"code", "message"}}.
      throw std::runtime_error("GET " + target + ": " + std::to_string(response.result_int()) +
                               " " + response.body());
    }
    return nlohmann::json::parse(response.body());
  }

 private:
  std::string host_;
  net::io_context ioc_;
  beast::tcp_stream stream_;
  beast::flat_buffer buffer_;
};

/// The .aara header: a type name and the array's sizes; `offset` is where the elements start.
struct AaraHeader {
  std::string type;
  std::vector<std::int32_t> sizes;
  std::size_t offset = 0;
};

std::int32_t littleInt32(const unsigned char* p) {
  return static_cast<std::int32_t>(
      static_cast<std::uint32_t>(p[0]) | static_cast<std::uint32_t>(p[1]) << 8 |
      static_cast<std::uint32_t>(p[2]) << 16 | static_cast<std::uint32_t>(p[3]) << 24);
}

float littleFloat(const unsigned char* p) {
  const auto bits = static_cast<std::uint32_t>(littleInt32(p));
  float value = 0;
  std::memcpy(&value, &bits, sizeof value);
  return value;
}

/// Byte n, n bytes of type name, byte d, d little-endian int32 sizes (13 bytes for a V3f grid).
AaraHeader decodeAaraHeader(const std::string& bytes) {
  const auto* data = reinterpret_cast<const unsigned char*>(bytes.data());
  if (bytes.empty() || bytes.size() < 2u + data[0]) {
    throw std::runtime_error(".aara: too short");
  }
  AaraHeader header;
  const std::size_t n = data[0];
  header.type.assign(bytes.data() + 1, n);
  const std::size_t dims = data[1 + n];
  header.offset = 2 + n + 4 * dims;
  if (bytes.size() < header.offset) {
    throw std::runtime_error(".aara: truncated header");
  }
  for (std::size_t i = 0; i < dims; ++i) {
    header.sizes.push_back(littleInt32(data + 2 + n + 4 * i));
  }
  return header;
}

int run(int argc, char** argv) {
  std::string host = "127.0.0.1";
  std::string port = "8080";
  std::vector<std::string> positional;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if ((arg == "--host" || arg == "--port") && i + 1 < argc) {
      (arg == "--host" ? host : port) = argv[++i];
    } else if (arg == "--help" || arg == "-h") {
      std::cout << "usage: vsm_client_example [--host HOST] [--port PORT] [MODEL [PATCH]]\n";
      return 0;
    } else {
      positional.push_back(arg);
    }
  }

  VsmConnection vsmd(host, port);
  const nlohmann::json models = vsmd.getJson("/v1/models")["models"];
  for (const auto& m : models) {
    std::cout << "model " << m["id"].get<std::string>() << ": version " << m["version"] << ", "
              << m["patches"] << " patches, depth " << m["depth"] << ", grid " << m["grid_size"]
              << "\n";
  }
  std::cout << "models: " << models.size() << "\n";
  if (models.empty() && positional.empty()) {
    return 0;
  }
  const std::string model =
      positional.size() > 0 ? positional[0] : models.at(0)["id"].get<std::string>();
  const std::string key = positional.size() > 1 ? positional[1] : "0_0_0";

  // Model ids are [A-Za-z0-9_-] and keys digits and '_': nothing to percent-encode.
  const std::string target = "/v1/models/" + model + "/patches/" + key + "/positions";
  auto response = vsmd.get(target);
  if (response.result_int() != 200) {
    throw std::runtime_error("GET " + target + ": " + std::to_string(response.result_int()) + " " +
                             response.body());
  }
  const std::string& bytes = response.body();
  const AaraHeader header = decodeAaraHeader(bytes);
  std::size_t count = 1;
  for (const std::int32_t size : header.sizes) {
    count *= static_cast<std::size_t>(size);
  }
  if (header.type != "V3f" || header.sizes.size() != 2 ||
      bytes.size() != header.offset + count * 12) {
    throw std::runtime_error("positions: expected a V3f grid, got " + header.type + " in " +
                             std::to_string(bytes.size()) + " bytes");
  }
  std::size_t defined = 0;
  double sum[3] = {0, 0, 0};
  const auto* p = reinterpret_cast<const unsigned char*>(bytes.data()) + header.offset;
  for (std::size_t i = 0; i < count; ++i, p += 12) {
    const float x = littleFloat(p);
    if (std::isnan(x)) {
      continue;
    }
    ++defined;
    sum[0] += x;
    sum[1] += littleFloat(p + 4);
    sum[2] += littleFloat(p + 8);
  }
  std::cout << "patch " << model << "/" << key << ": " << bytes.size() << " bytes, etag "
            << response[http::field::etag] << "\n";
  std::cout << "aara header: type " << header.type << ", " << header.sizes[0] << " x "
            << header.sizes[1] << ", data at byte " << header.offset << "\n";
  std::cout << "vertices: " << count << ", defined " << defined;
  if (defined > 0) {
    std::cout << ", local centre " << sum[0] / defined << " " << sum[1] / defined << " "
              << sum[2] / defined;
  }
  std::cout << "\nlocal2global: " << response["X-VSM-Local2Global"] << "\n";
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {
    std::cerr << "vsm_client_example: " << e.what() << "\n";
    return 1;
  }
}
