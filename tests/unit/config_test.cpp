// The daemon's configuration (server/config): sizes and durations as written, listen addresses,
// the file, the command line and --set, the token, validation and describe().
#include <gtest/gtest.h>

#include <cstddef>
#include <string>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/opc/texture_file.hpp"
#include "server/config/config.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::server {
namespace {

using core::ErrorCode;
using core::test::errorOf;
using core::test::TempFile;
using namespace std::chrono_literals;
using nlohmann::json;

constexpr std::size_t kKiB = 1024;
constexpr std::size_t kMiB = 1024 * kKiB;
constexpr std::size_t kGiB = 1024 * kMiB;

TEST(ConfigSize, AcceptsBytesAndBinaryAndDecimalSuffixes) {
  EXPECT_EQ(parseSize("1048576"), 1048576u);
  EXPECT_EQ(parseSize("0"), 0u);
  EXPECT_EQ(parseSize("512B"), 512u);
  EXPECT_EQ(parseSize("4KiB"), 4 * kKiB);
  EXPECT_EQ(parseSize("64MiB"), 64 * kMiB);
  EXPECT_EQ(parseSize("2GiB"), 2 * kGiB);
  EXPECT_EQ(parseSize("1TiB"), 1024 * kGiB);
  EXPECT_EQ(parseSize("3KB"), 3000u);
  EXPECT_EQ(parseSize("5MB"), 5'000'000u);
  EXPECT_EQ(parseSize("1GB"), 1'000'000'000u);
  EXPECT_EQ(parseSize(" 2 gib "), 2 * kGiB);
  EXPECT_EQ(parseSize("1.5GiB"), 3 * kGiB / 2);
}

TEST(ConfigSize, RejectsJunkNegativesAndOverflow) {
  for (const char* text : {"", "MiB", "-1", "1XB", "1.2.3MiB", "1 K", "0x10", "99999999999TiB",
                           "18446744073709551616"}) {
    EXPECT_EQ(errorOf([&] { parseSize(text); }).first, ErrorCode::InvalidArgument) << text;
  }
}

TEST(ConfigSize, FormatRoundTrips) {
  for (const std::size_t bytes :
       {std::size_t{0}, std::size_t{1000}, 4 * kKiB, 64 * kMiB, 3 * kGiB, kGiB + 1, 1536 * kMiB}) {
    EXPECT_EQ(parseSize(formatSize(bytes)), bytes) << formatSize(bytes);
  }
  EXPECT_EQ(formatSize(64 * kMiB), "64MiB");
  EXPECT_EQ(formatSize(1000), "1000");
}

TEST(ConfigDuration, AcceptsSecondsAndSuffixes) {
  EXPECT_EQ(parseDuration("30"), 30s);
  EXPECT_EQ(parseDuration("30s"), 30s);
  EXPECT_EQ(parseDuration("250ms"), 250ms);
  EXPECT_EQ(parseDuration("0.5"), 500ms);
  EXPECT_EQ(parseDuration("2m"), 120s);
  EXPECT_EQ(parseDuration("1h"), 3600s);
  for (const char* text : {"", "s", "-1", "5d", "1.5.2s"}) {
    EXPECT_EQ(errorOf([&] { parseDuration(text); }).first, ErrorCode::InvalidArgument) << text;
  }
  EXPECT_EQ(formatDuration(30s), "30s");
  EXPECT_EQ(formatDuration(250ms), "250ms");
}

TEST(ListenAddress, ParsesHostAndPortAndRoundTrips) {
  EXPECT_EQ(ListenAddress::parse("127.0.0.1:8080"), (ListenAddress{"127.0.0.1", 8080}));
  EXPECT_EQ(ListenAddress::parse("[::1]:0"), (ListenAddress{"::1", 0}));
  EXPECT_EQ(ListenAddress::parse("localhost:65535").port, 65535);
  for (const char* text : {"127.0.0.1:8080", "[::1]:0", "0.0.0.0:1"}) {
    EXPECT_EQ(ListenAddress::parse(text).toString(), text);
  }
  for (const char* text : {"", "host", ":80", "::1:80", "h:65536", "h:-1", "h:8o", "[]:80"}) {
    EXPECT_EQ(errorOf([&] { ListenAddress::parse(text); }).first, ErrorCode::InvalidArgument)
        << text;
  }
}

TEST(Config, DefaultsAreValid) {
  const Config config;
  EXPECT_NO_THROW(config.validate());
  EXPECT_EQ(config.listen.toString(), "127.0.0.1:8080");
  EXPECT_EQ(config.memoryBudget, kGiB);
  EXPECT_TRUE(config.token.empty());
  // The limits' defaults are those of the components that enforce them.
  EXPECT_EQ(config.limits.bodyBytes, http::ServerOptions{}.bodyLimit);
  EXPECT_EQ(config.limits.connectionsPerClient, 256u);
  EXPECT_EQ(config.limits.eventSubscribers, 64u);
  EXPECT_EQ(config.limits.eventSubscribersPerClient, 8u);
}

TEST(Config, FlagsOverrideTheFileWhateverTheirOrder) {
  const TempFile file(R"({"memory_budget": "2GiB", "listen": "0.0.0.0:9000",
                          "limits": {"body_bytes": "4KiB"}, "threads.cpu": 3})");
  const CommandLine cl = parseCommandLine(
      {"--memory-budget", "64MiB", "--config", file.path(), "--listen=127.0.0.1:0"});
  EXPECT_EQ(cl.config.memoryBudget, 64 * kMiB);
  EXPECT_EQ(cl.config.listen, (ListenAddress{"127.0.0.1", 0}));
  EXPECT_EQ(cl.config.limits.bodyBytes, 4 * kKiB);  // only in the file
  EXPECT_EQ(cl.config.threads.cpu, 3u);             // a dotted key in the file
}

TEST(Config, FileTakesNumbersStringsDurationsAndComments) {
  const TempFile file(R"({
    // comments are allowed
    "data_root": "/srv/vsm",
    "token": "abc-123",
    "log_level": "debug",
    "cache_policy": "fifo-second-chance",
    "limits": {"read_timeout": 5, "idle_timeout": "750ms", "connections": 7,
               "header_bytes": 8192, "shutdown_grace": "1m", "header_timeout": "2s",
               "connections_per_client": 3, "event_subscribers_per_client": 5}
  })");
  const Config config = parseCommandLine({"--config", file.path()}).config;
  EXPECT_EQ(config.dataRoot, "/srv/vsm");
  EXPECT_EQ(config.token, "abc-123");
  EXPECT_EQ(config.logLevel, core::log::Level::Debug);
  EXPECT_EQ(config.cachePolicy, core::EvictionPolicy::FifoSecondChance);
  EXPECT_EQ(config.limits.readTimeout, 5s);
  EXPECT_EQ(config.limits.idleTimeout, 750ms);
  EXPECT_EQ(config.limits.connections, 7u);
  EXPECT_EQ(config.limits.headerBytes, 8 * kKiB);
  EXPECT_EQ(config.limits.shutdownGrace, 60s);
  EXPECT_EQ(config.limits.headerTimeout, 2s);
  EXPECT_EQ(config.limits.connectionsPerClient, 3u);
  EXPECT_EQ(config.limits.eventSubscribersPerClient, 5u);
}

TEST(Config, TheTokenComesFromTheFirstLineOfATokenFile) {
  const TempFile file("tok-en_1\nsecond line is ignored\n");
  const Config config = parseCommandLine({"--token-file", file.path()}).config;
  EXPECT_EQ(config.token, "tok-en_1");
  EXPECT_EQ(config.tokenFile, file.path());
  const TempFile inConfig("{\"token_file\": \"" + file.path() + "\"}");
  EXPECT_EQ(parseCommandLine({"--config", inConfig.path()}).config.token, "tok-en_1");
  const TempFile crlf("tok-en_2 \r\n");
  EXPECT_EQ(parseCommandLine({"--token-file", crlf.path()}).config.token, "tok-en_2");
}

TEST(Config, ABadTokenFileIsAClearError) {
  auto [code, message] = errorOf([] { parseCommandLine({"--token-file", "/nonexistent/tok"}); });
  EXPECT_EQ(code, ErrorCode::NotFound);
  EXPECT_NE(message.find("token file '/nonexistent/tok' not found"), std::string::npos) << message;
  const TempFile empty("\n");
  std::tie(code, message) = errorOf([&] { parseCommandLine({"--token-file", empty.path()}); });
  EXPECT_EQ(code, ErrorCode::InvalidArgument);
  EXPECT_NE(message.find("is empty"), std::string::npos) << message;
  const TempFile good("abc");
  std::tie(code, message) = errorOf([&] {
    parseCommandLine({"--token-file", good.path(), "--token", "abc"});
  });
  EXPECT_EQ(code, ErrorCode::InvalidArgument);
  EXPECT_NE(message.find("not both"), std::string::npos) << message;
  const TempFile bad("sec ret");
  std::tie(code, message) = errorOf([&] { parseCommandLine({"--token-file", bad.path()}); });
  EXPECT_EQ(code, ErrorCode::InvalidArgument);
  EXPECT_EQ(message.find("sec ret"), std::string::npos) << message;
  const TempFile huge(std::string(2000, 'a'));
  EXPECT_EQ(errorOf([&] {
              parseCommandLine({"--token-file", huge.path()});
            }).first,
            ErrorCode::InvalidArgument);
}

TEST(Config, SetReachesEveryKeyFromTheCommandLine) {
  const Config config =
      parseCommandLine({"--set", "limits.pipelined_responses=3", "--set", "threads.jobs=5", "--set",
                        "limits.texture_pixels=4096", "--token", "t0k3n", "--port-file", "/tmp/p",
                        "--log-level", "warn"})
          .config;
  EXPECT_EQ(config.limits.pipelinedResponses, 3u);
  EXPECT_EQ(config.limits.texturePixels, 4096u);
  EXPECT_EQ(Config{}.limits.texturePixels, core::kDefaultTexturePixels);
  EXPECT_EQ(config.threads.jobs, 5u);
  EXPECT_EQ(config.token, "t0k3n");
  EXPECT_EQ(config.portFile, "/tmp/p");
  EXPECT_EQ(config.logLevel, core::log::Level::Warn);
}

TEST(Config, ADeeplyNestedOrHugeFileIsRefusedBeforeItIsUsed) {
  const TempFile deep(std::string(100000, '[') + std::string(100000, ']'));
  auto [code, message] = errorOf([&] { parseCommandLine({"--config", deep.path()}); });
  EXPECT_EQ(code, ErrorCode::InvalidArgument);
  EXPECT_NE(message.find("nests deeper than 8 levels"), std::string::npos) << message;
  const TempFile nine(R"({"a": {"b": {"c": {"d": {"e": {"f": {"g": {"h": {"i": 1}}}}}}}}})");
  std::tie(code, message) = errorOf([&] { parseCommandLine({"--config", nine.path()}); });
  EXPECT_NE(message.find("nests deeper"), std::string::npos) << message;
  const TempFile huge("{\"listen\": \"127.0.0.1:0\"" + std::string(2 << 20, ' ') + "}");
  std::tie(code, message) = errorOf([&] { parseCommandLine({"--config", huge.path()}); });
  EXPECT_EQ(code, ErrorCode::InvalidArgument);
  EXPECT_NE(message.find("larger than 1 MiB"), std::string::npos) << message;
  const TempFile nested(R"({"limits": {"body_bytes": "2MiB"}})");
  EXPECT_EQ(parseCommandLine({"--config", nested.path()}).config.limits.bodyBytes, 2u << 20);
}

TEST(Config, TheClusterFlagsSetTheClusterKeysAndBadOnesAreRefused) {
  const Config config =
      parseCommandLine({"--coordinator", "http://127.0.0.1:2379", "--node", "n-1_a", "--advertise",
                        "http://[::1]:8081", "--set", "cluster.lease_ttl=4s"})
          .config;
  EXPECT_EQ(config.cluster.coordinator, "http://127.0.0.1:2379");
  EXPECT_EQ(config.cluster.node, "n-1_a");
  EXPECT_EQ(config.cluster.advertise, "http://[::1]:8081");
  EXPECT_EQ(config.cluster.leaseTtl, std::chrono::seconds(4));
  EXPECT_TRUE(Config{}.cluster.coordinator.empty()) << "alone by default";
  const std::vector<std::vector<std::string>> bad = {
      {"--coordinator", "127.0.0.1:2379"},      {"--coordinator", "https://etcd:2379"},
      {"--coordinator", "http://etcd:2379/v3"}, {"--coordinator", "http://:2379"},
      {"--advertise", "http://node"},           {"--node", "n/1"},
      {"--node", std::string(33, 'n')},         {"--set", "cluster.lease_ttl=1s"},
  };
  for (const auto& args : bad) {
    const auto [code, message] = errorOf([&] { parseCommandLine(args); });
    EXPECT_EQ(code, ErrorCode::InvalidArgument) << args[0] << " " << args[1];
    EXPECT_NE(message.find("cluster."), std::string::npos) << message;
  }
}

TEST(Config, UnknownKeysAndBadValuesNameTheKey) {
  const TempFile typo(R"({"limits": {"body_byte": 10}})");
  auto [code, message] = errorOf([&] { parseCommandLine({"--config", typo.path()}); });
  EXPECT_EQ(code, ErrorCode::InvalidArgument);
  EXPECT_NE(message.find("limits.body_byte"), std::string::npos) << message;

  std::tie(code, message) = errorOf([] { parseCommandLine({"--memory-budget", "lots"}); });
  EXPECT_EQ(code, ErrorCode::InvalidArgument);
  EXPECT_NE(message.find("memory_budget"), std::string::npos) << message;

  const TempFile wrongType(R"({"limits": {"connections": -3}})");
  EXPECT_EQ(errorOf([&] {
              parseCommandLine({"--config", wrongType.path()});
            }).first,
            ErrorCode::InvalidArgument);
  const TempFile notObject(R"([1, 2])");
  EXPECT_EQ(errorOf([&] {
              parseCommandLine({"--config", notObject.path()});
            }).first,
            ErrorCode::InvalidArgument);
  const TempFile notJson(R"({"listen": )");
  EXPECT_EQ(errorOf([&] {
              parseCommandLine({"--config", notJson.path()});
            }).first,
            ErrorCode::InvalidArgument);
  EXPECT_EQ(errorOf([] {
              parseCommandLine({"--config", "/nonexistent/vsmd.json"});
            }).first,
            ErrorCode::NotFound);
}

TEST(Config, ValidationRejectsOutOfRangeValues) {
  const std::vector<std::vector<std::string>> cases = {
      {"--set", "limits.connections=0"},
      {"--set", "limits.body_bytes=0"},
      {"--set", "limits.header_bytes=10"},
      {"--set", "limits.idle_timeout=0"},
      {"--set", "threads.io=0"},
      {"--set", "limits.pipelined_responses=1000"},
      {"--set", "limits.texture_pixels=0"},
      {"--memory-budget", "1000"},
      {"--data-root", ""},
      {"--set", "limits.header_timeout=0"},
      {"--set", "limits.connections_per_client=0"},
      {"--set", "limits.event_subscribers_per_client=100001"},
  };
  for (const auto& args : cases) {
    const auto [code, message] = errorOf([&] { parseCommandLine(args); });
    EXPECT_EQ(code, ErrorCode::InvalidArgument) << args[1];
    const std::string key = args[1].substr(0, args[1].find('='));
    if (args[0] == "--set") {
      EXPECT_NE(message.find(key), std::string::npos) << message;
    }
  }
}

TEST(Config, ABadTokenIsRejectedWithoutEchoingIt) {
  const auto [code, message] = errorOf([] { parseCommandLine({"--token", "sec ret"}); });
  EXPECT_EQ(code, ErrorCode::InvalidArgument);
  EXPECT_EQ(message.find("sec ret"), std::string::npos) << message;
}

TEST(Config, UnknownFlagsAndMissingValuesAreUsageErrors) {
  EXPECT_EQ(errorOf([] { parseCommandLine({"--frobnicate"}); }).first, ErrorCode::InvalidArgument);
  EXPECT_EQ(errorOf([] { parseCommandLine({"--listen"}); }).first, ErrorCode::InvalidArgument);
  EXPECT_EQ(errorOf([] {
              parseCommandLine({"--set", "novalue"});
            }).first,
            ErrorCode::InvalidArgument);
  EXPECT_TRUE(parseCommandLine({"--help"}).help);
  EXPECT_TRUE(parseCommandLine({"--version"}).version);
}

TEST(Config, DescribeListsEveryKeyAndRedactsTheToken) {
  Config config;
  config.token = "super-secret";
  const auto pairs = config.describe();
  std::string all;
  for (const auto& [key, value] : pairs) {
    all += key + "=" + value + "\n";
  }
  EXPECT_EQ(all.find("super-secret"), std::string::npos);
  EXPECT_NE(all.find("token=(redacted)"), std::string::npos);
  EXPECT_NE(all.find("limits.body_bytes=1MiB"), std::string::npos);
  // describe() prints what set() reads back.
  Config copy;
  for (const auto& [key, value] : pairs) {
    if (key != "token" && key != "token_file" && key != "port_file" && key != "viewer_dir") {
      copy.set(key, json(value));
    }
  }
  EXPECT_EQ(copy.describe(), Config{}.describe());
}

// --- router ---------------------------------------------------------------------------------

}  // namespace
}  // namespace vsm::server
