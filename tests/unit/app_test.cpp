// server/app: the descriptor plan.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstddef>

#include "server/app/application.hpp"

namespace vsm::server {
namespace {

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

}  // namespace
}  // namespace vsm::server
