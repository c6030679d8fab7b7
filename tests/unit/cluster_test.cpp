// server/cluster: what can be tested without etcd.
#include <gtest/gtest.h>

#include <string>
#include <utility>

#include "core/common/error.hpp"
#include "server/cluster/etcd_client.hpp"

namespace vsm::server {
namespace {

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

}  // namespace
}  // namespace vsm::server
