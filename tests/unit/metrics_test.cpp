// server/metrics: the registry and its text format.
#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "server/metrics/metrics.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::server {
namespace {

using core::ErrorCode;
using core::test::errorOf;

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

}  // namespace
}  // namespace vsm::server
