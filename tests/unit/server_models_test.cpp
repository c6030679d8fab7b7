// The daemon's model registry, job registry and model/job routes, in-process: a synthetic OPC in a
// temporary data root, requests through the real Router and Pipeline (no sockets).
#include <gtest/gtest.h>

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <mutex>
#include <span>
#include <thread>

#include <nlohmann/json.hpp>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/stored_file.hpp"
#include "core/opc/validate.hpp"
#include "core/store/live_model.hpp"
#include "core/store/model_edit.hpp"
#include "core/tiles/glb.hpp"
#include "server/api/job_routes.hpp"
#include "server/api/model_routes.hpp"
#include "server/api/terrain_routes.hpp"
#include "server/api/tiles_routes.hpp"
#include "server/exec/work_pool.hpp"
#include "server/http/pipeline.hpp"
#include "server/http/router.hpp"
#include "server/jobs/job_registry.hpp"
#include "server/jobs/model_jobs.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"
#include "server/models/patch_data.hpp"
#include "tests/unit/test_support.hpp"

namespace fs = std::filesystem;

namespace vsm::server {
namespace {

using core::Error;
using core::ErrorCode;
using core::test::codeOf;
using nlohmann::json;
using namespace std::chrono_literals;

constexpr int kSize = 17;  // 2^4 + 1
constexpr std::size_t kMiB = 1024 * 1024;

/// Leaf (x, y) at depth 2 of a 4x4 bottom level on a 1 m lattice; leaf (3, 3) is left out.
std::shared_ptr<core::PatchGrid> leafGrid(std::uint32_t x, std::uint32_t y) {
  const int u0 = static_cast<int>(x) * (kSize - 1);
  const int v0 = static_cast<int>(y) * (kSize - 1);
  auto grid =
      std::make_shared<core::PatchGrid>(kSize, core::Mat4d::translation({u0 + 8.0, v0 + 8.0, 0}));
  for (int j = 0; j < kSize; ++j) {
    for (int i = 0; i < kSize; ++i) {
      grid->setGlobal(i, j, {double(u0 + i), double(v0 + j), std::sin((u0 + i) * 0.2) * 5});
    }
  }
  return grid;
}

/// Writes a three-level model (15 leaves, 4 + 1 overviews) to `dir`.
void writeModel(const fs::path& dir) {
  core::Model model(kSize);
  const auto info = [](const core::PatchKey& key) {
    core::PatchInfo i;
    i.key = key;
    return i;
  };
  model.insert(info(core::PatchKey::root()));
  for (std::uint32_t y = 0; y < 2; ++y) {
    for (std::uint32_t x = 0; x < 2; ++x) {
      model.insert(info({1, x, y}));
    }
  }
  for (std::uint32_t y = 0; y < 4; ++y) {
    for (std::uint32_t x = 0; x < 4; ++x) {
      if (x == 3 && y == 3) {
        continue;
      }
      model.insert(info({2, x, y}));
      model.setGrid({2, x, y}, leafGrid(x, y));
    }
  }
  model.refreshStale([](const core::PatchInfo&) { return nullptr; });
  core::OpcWriter writer(dir, core::OpcWriter::Durability::EachFile);
  for (const auto& [key, patch] : model.patches()) {
    core::PatchInfo& mutableInfo = model.at(key);
    mutableInfo.folder = key.toString();
    writer.writePatch(mutableInfo, *patch.grid, model.childrenBox(key));
  }
  writer.writeHierarchy(model);
}

/// A temporary data root, removed at the end of the test.
class DataRoot {
 public:
  DataRoot()
      : path_(fs::temp_directory_path() / ("vsm_server_models_test_" + std::to_string(getpid()) +
                                           "_" + std::to_string(counter_++))) {
    fs::remove_all(path_);
    fs::create_directories(path_);
    path_ = fs::canonical(path_);
  }
  ~DataRoot() { fs::remove_all(path_); }
  const fs::path& path() const { return path_; }

 private:
  static inline int counter_ = 0;
  fs::path path_;
};

http::Request request(http::Method method, std::string target, std::string body = {}) {
  http::Request r;
  r.method = method;
  r.methodName = std::string(http::toString(method));
  r.target = std::move(target);
  r.body = std::move(body);
  r.id = "req-1";
  if (!r.body.empty()) {
    r.headers.emplace_back("content-type", "application/json");
  }
  return r;
}

// ---- ids and paths ---------------------------------------------------------------------------

TEST(ModelId, AcceptsOnlyShortWordsWithDashes) {
  for (const std::string& id :
       {std::string("a"), std::string("prism_65"), std::string("Jacks-boro"), std::string("0"),
        std::string(64, 'x')}) {
    EXPECT_TRUE(models::isValidModelId(id)) << id;
  }
  for (const std::string& id : {std::string(), std::string(65, 'x'), std::string("a.b"),
                                std::string("a/b"), std::string(".."), std::string("a b"),
                                std::string("a%2F"), std::string("é"), std::string("a\0b", 3)}) {
    EXPECT_FALSE(models::isValidModelId(id)) << id;
    EXPECT_EQ(codeOf([&] { models::checkModelId(id); }), ErrorCode::InvalidArgument);
  }
}

TEST(ResolveInside, KeepsPathsInsideTheDataRoot) {
  const DataRoot root;
  fs::create_directories(root.path() / "a" / "b");
  EXPECT_EQ(models::resolveInside(root.path(), "a/b"), root.path() / "a" / "b");
  EXPECT_EQ(models::resolveInside(root.path(), "a/./b/"), root.path() / "a" / "b");
  EXPECT_EQ(models::resolveInside(root.path(), "new.tif"), root.path() / "new.tif");
  for (const std::string& bad :
       {std::string(), std::string("/etc"), std::string(".."), std::string("../x"),
        std::string("a/../../x"), std::string("a/.."), std::string("."), std::string("a\0b", 3)}) {
    EXPECT_EQ(codeOf([&] { models::resolveInside(root.path(), bad); }), ErrorCode::InvalidArgument)
        << bad;
  }
}

TEST(ResolveInside, RejectsSymbolicLinksOutOfTheRoot) {
  const DataRoot root;
  const DataRoot outside;
  fs::create_directory_symlink(outside.path(), root.path() / "out");
  fs::create_directory_symlink(root.path() / "in", root.path() / "alias");
  fs::create_directories(root.path() / "in");
  EXPECT_EQ(codeOf([&] { models::resolveInside(root.path(), "out"); }), ErrorCode::InvalidArgument);
  EXPECT_EQ(codeOf([&] { models::resolveInside(root.path(), "out/x.tif"); }),
            ErrorCode::InvalidArgument);
  EXPECT_EQ(models::resolveInside(root.path(), "alias"), root.path() / "in");
}

// ---- registry --------------------------------------------------------------------------------

TEST(ModelRegistry, OpensEveryOpcUnderTheRootAndSkipsTheRest) {
  const DataRoot root;
  writeModel(root.path() / "good");
  writeModel(root.path() / "bad.id");
  fs::create_directories(root.path() / "empty");
  fs::create_directories(root.path() / "broken" / "Patches");
  { std::ofstream(root.path() / "broken" / "Patches" / "patchhierarchy.xml") << "<not xml"; }
  core::PatchCache cache(64 * kMiB);
  models::ModelRegistry registry(root.path(), cache);
  EXPECT_EQ(registry.openAll(), 1u);
  ASSERT_EQ(registry.list().size(), 1u);
  EXPECT_EQ(registry.list()[0]->name(), "good");
  EXPECT_EQ(registry.get("good")->snapshot()->model->patchCount(), 20u);
  EXPECT_EQ(codeOf([&] { registry.get("bad.id"); }), ErrorCode::NotFound);
}

TEST(ModelRegistry, IdsAndDirectoriesAreOpenOnceAndLeasesBlockClosing) {
  const DataRoot root;
  writeModel(root.path() / "m");
  core::PatchCache cache(64 * kMiB);
  models::ModelRegistry registry(root.path(), cache);
  registry.open("m", root.path() / "m");
  EXPECT_EQ(codeOf([&] { registry.open("m", root.path() / "m"); }), ErrorCode::Conflict);
  EXPECT_EQ(codeOf([&] { registry.open("other", root.path() / "m"); }), ErrorCode::Conflict);
  EXPECT_EQ(codeOf([&] { registry.open("x", root.path() / "missing"); }), ErrorCode::NotFound);
  EXPECT_EQ(codeOf([&] { registry.reserve("m"); }), ErrorCode::Conflict);
  {
    const auto lease = registry.lease("m");
    EXPECT_EQ(codeOf([&] { registry.close("m"); }), ErrorCode::Conflict);
  }
  const auto held = registry.get("m");
  registry.close("m");
  EXPECT_EQ(registry.find("m"), nullptr);
  EXPECT_EQ(codeOf([&] { registry.close("m"); }), ErrorCode::NotFound);
  // A request that still holds the closed model reads on.
  EXPECT_TRUE(held->positions(*held->snapshot(), core::PatchKey::root()));
}

TEST(ModelRegistry, AReservedIdOpensOnlyForItsHolder) {
  const DataRoot root;
  writeModel(root.path() / "m");
  core::PatchCache cache(64 * kMiB);
  models::ModelRegistry registry(root.path(), cache);
  {
    const auto reservation = registry.reserve("m");
    EXPECT_EQ(codeOf([&] { registry.reserve("m"); }), ErrorCode::Conflict);
    EXPECT_EQ(codeOf([&] { registry.open("m", root.path() / "m"); }), ErrorCode::Conflict);
    registry.openReserved(reservation, root.path() / "m");
    EXPECT_EQ(codeOf([&] { registry.close("m"); }), ErrorCode::Conflict);
  }
  registry.close("m");
  const auto reservation = registry.reserve("m");  // free again
}

// Issue 32, finding 8: limits.models bounds the models open at once (each writable one holds its
// writer lock's descriptor, counted in the descriptor plan): at the bound, one more model is
// skipped at start, an import's reservation or an open is refused, and closing one makes room.
TEST(ModelRegistry, ModelsOpenAtOnceStopAtTheLimit) {
  const DataRoot root;
  for (const char* id : {"a", "b", "c"}) {
    writeModel(root.path() / id);
  }
  core::PatchCache cache(64 * kMiB);
  models::ModelRegistry registry(root.path(), cache);
  registry.limitModels(2);
  EXPECT_EQ(registry.openAll(), 2u);
  EXPECT_EQ(registry.ids(), (std::vector<std::string>{"a", "b"}));
  EXPECT_EQ(codeOf([&] { registry.reserve("d"); }), ErrorCode::Conflict);
  EXPECT_EQ(codeOf([&] { registry.open("c", root.path() / "c"); }), ErrorCode::Conflict);
  registry.close("a");
  {
    // A reservation takes the place: an open beside it is refused, its holder opens.
    const auto reservation = registry.reserve("d");
    EXPECT_EQ(codeOf([&] { registry.open("c", root.path() / "c"); }), ErrorCode::Conflict);
    writeModel(root.path() / "d");
    registry.openReserved(reservation, root.path() / "d");
  }
  EXPECT_EQ(registry.ids(), (std::vector<std::string>{"b", "d"}));
  EXPECT_EQ(codeOf([&] { registry.reserve("e"); }), ErrorCode::Conflict);
  registry.close("b");
  EXPECT_EQ(registry.open("c", root.path() / "c")->name(), "c");
}

// ---- encoded responses -------------------------------------------------------------------------

std::vector<std::byte> bytesOf(std::string_view text) {
  const auto span = std::as_bytes(std::span(text.data(), text.size()));
  return {span.begin(), span.end()};
}

// Issue 32, finding 8: a followed version names the patches it removed (a restore), as the
// writer's own publish does.
TEST(ModelRegistry, AFollowedRestoreNamesThePatchesItRemoved) {
  DataRoot root;
  writeModel(root.path() / "m");
  core::PatchCache cache(64 * kMiB);
  // Another writer holds the model: the registry opens it for reading and follows it.
  const auto writer = core::LiveModel::open(root.path() / "m", "writer", cache);
  const std::uint64_t v = writer->snapshot()->version;
  models::ModelRegistry registry(root.path(), cache);
  std::vector<models::ModelRegistry::Publication> told;
  registry.onPublished([&](const models::ModelRegistry::Publication& p) { told.push_back(p); });
  ASSERT_EQ(registry.openAll(), 1u);
  ASSERT_FALSE(registry.get("m")->writable());
  const core::PatchKey added{3, 2, 4};  // a level below leaf 2_1_2
  {
    auto edit = writer->beginEdit();
    edit->setPositions(added, leafGrid(1, 2));
    edit->publish();
  }
  ASSERT_EQ(registry.follow(), 1u);
  {
    auto edit = writer->beginEdit();
    edit->restore(*writer->snapshotAt(v));
    edit->publish();
  }
  ASSERT_EQ(registry.follow(), 1u);
  ASSERT_EQ(told.size(), 2u);
  EXPECT_TRUE(told[0].followed);
  EXPECT_NE(std::find(told[0].changed.begin(), told[0].changed.end(), added),
            told[0].changed.end());
  EXPECT_TRUE(told[0].removed.empty());
  EXPECT_EQ(told[1].version, v + 2);
  EXPECT_EQ(told[1].removed, std::vector<core::PatchKey>{added});
}

// Issue 32, finding 2: a follower refuses a version committed under a fencing token older than
// one it has seen for the model (a writer that had lost the model committed it), keeps serving
// what it served, counts it, and follows the next version of a current writer.
TEST(ModelRegistry, AFollowerRefusesAVersionWhoseFencingTokenIsOlderThanOneSeen) {
  DataRoot root;
  writeModel(root.path() / "m");
  core::PatchCache cache(64 * kMiB);
  auto writer = core::LiveModel::open(root.path() / "m", "writer", cache);
  models::ModelRegistry registry(root.path(), cache);
  ASSERT_EQ(registry.openAll(), 1u);
  ASSERT_FALSE(registry.get("m")->writable());
  const fs::path hierarchy = root.path() / "m" / "Patches" / "patchhierarchy.xml";
  // What a writer that lost the model commits when its check of the token on disk came just
  // before the new writer's publish: here the last revision's token rewritten to `takeover`.
  auto forgeTakeover = [&](std::uint64_t takeover) {
    std::ifstream in(hierarchy);
    std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    const auto at = text.find("<Takeover>");
    ASSERT_NE(at, std::string::npos);
    const auto end = text.find("</Takeover>", at);
    text.replace(at, end - at, "<Takeover>" + std::to_string(takeover));
    std::ofstream(root.path() / "m" / "Patches" / "forged.xml") << text;
    fs::rename(root.path() / "m" / "Patches" / "forged.xml", hierarchy);
    writer = writer->reopen();
  };
  auto publishUnder = [&](std::optional<core::FencingToken> token, double bump) {
    auto edit = writer->beginEdit();
    auto grid = std::make_shared<core::PatchGrid>(*leafGrid(1, 2));
    grid->setGlobal(3, 3, grid->global(3, 3) + core::Vec3d{0, 0, bump});
    edit->setPositions({2, 1, 2}, grid);
    core::PublishOptions options;
    options.token = token;
    edit->publish(nullptr, options);
    return writer->snapshot()->version;
  };
  // Node b took the model over at etcd revision 90 and published: followed.
  const std::uint64_t byB = publishUnder(core::FencingToken{90, 2}, 1);
  ASSERT_EQ(registry.follow(), 1u);
  ASSERT_EQ(registry.get("m")->snapshot()->version, byB);
  // Node a, which had claimed it at revision 50 and lost it, commits anyway: not followed.
  const std::uint64_t byA = publishUnder(core::FencingToken{90, 2}, 2);
  forgeTakeover(50);
  EXPECT_EQ(registry.follow(), 0u);
  EXPECT_EQ(registry.get("m")->snapshot()->version, byB) << "followed a fenced-off writer";
  EXPECT_EQ(registry.followsRefused(), 1u);
  EXPECT_EQ(registry.get("m")->snapshot()->revision.fence, (core::FencingToken{90, 2}));
  ASSERT_GT(byA, byB);
  EXPECT_EQ(registry.follow(), 0u);
  EXPECT_EQ(registry.followsRefused(), 1u) << "a refused hierarchy is read again before it changes";
  // Node b publishes again (on top of what is on disk): followed, as is a version without a
  // token (a single node's, an older vsmd's).
  const std::uint64_t again = publishUnder(core::FencingToken{90, 2}, 3);
  EXPECT_EQ(registry.follow(), 1u);
  EXPECT_EQ(registry.get("m")->snapshot()->version, again);
  publishUnder(std::nullopt, 4);
  EXPECT_EQ(registry.follow(), 1u);
  EXPECT_EQ(registry.followsRefused(), 1u);
  // The token seen stays the newest: a version of the fenced-off writer after a token-less one is
  // still refused.
  publishUnder(core::FencingToken{90, 2}, 5);
  forgeTakeover(50);
  EXPECT_EQ(registry.follow(), 0u);
  EXPECT_EQ(registry.followsRefused(), 2u);
}

TEST(EncodedCache, BodiesAreTypedChargedAndPinnedWhileHeld) {
  const DataRoot root;
  writeModel(root.path() / "m");
  core::PatchCache cache(64 * kMiB);
  const auto live = core::LiveModel::open(root.path() / "m", "m", cache);
  const auto encoded = models::EncodedCache::create(cache, *live);
  const core::PatchKey key = core::PatchKey::root();
  EXPECT_EQ(encoded->find(key, 1, models::Encoding::Glb, true), nullptr);
  auto body = encoded->put(key, 1, models::Encoding::Glb, bytesOf("glTF..."), "note");
  EXPECT_EQ(body->text(), "glTF...");
  EXPECT_EQ(body->note(), "note");
  // One entry per encoding and version: a PNG of the same patch is another.
  EXPECT_EQ(encoded->find(key, 1, models::Encoding::TexturePng, true), nullptr);
  EXPECT_EQ(encoded->find(key, 2, models::Encoding::Glb, true), nullptr);
  auto again = encoded->find(key, 1, models::Encoding::Glb, true);
  ASSERT_NE(again, nullptr);
  EXPECT_EQ(again->text(), "glTF...");
  core::CacheStats stats = cache.stats();
  const auto encodedBytes =
      stats.residentByCategory[static_cast<std::size_t>(core::MemoryCategory::Encoded)];
  EXPECT_EQ(encodedBytes, 7u + 4u);  // the bytes and the note
  EXPECT_EQ(stats.residentByModel.at("m"), encodedBytes);
  EXPECT_EQ(stats.pinnedBytes, encodedBytes);  // held by `body` and `again`: a response in flight
  body.reset();
  EXPECT_EQ(cache.stats().pinnedBytes, encodedBytes);
  again.reset();
  EXPECT_EQ(cache.stats().pinnedBytes, 0u);
  EXPECT_EQ(cache.stats().residentBytes, encodedBytes);  // cached, no longer pinned
}

TEST(EncodedCache, AHeldBodyOutlivesPressureAndItsCacheStaysAliveWithIt) {
  const DataRoot root;
  writeModel(root.path() / "m");
  core::PatchCache cache(2 * kMiB);
  const auto live = core::LiveModel::open(root.path() / "m", "m", cache);
  auto encoded = models::EncodedCache::create(cache, *live);
  const std::vector<std::byte> big(900 * 1024, std::byte{7});
  const auto held = encoded->put({1, 0, 0}, 1, models::Encoding::PositionsAara, big);
  encoded->put({1, 1, 0}, 1, models::Encoding::PositionsAara, big);
  encoded->put({1, 0, 1}, 1, models::Encoding::PositionsAara, big);  // evicts (1, 1, 0) only
  EXPECT_NE(encoded->find({1, 0, 0}, 1, models::Encoding::PositionsAara, true), nullptr);
  EXPECT_EQ(encoded->find({1, 1, 0}, 1, models::Encoding::PositionsAara, true), nullptr);
  EXPECT_LE(cache.stats().residentBytes, 2 * kMiB);
  // Everything held: no room, and the answer is "retry", never an allocation beyond the budget.
  const auto second = encoded->find({1, 0, 1}, 1, models::Encoding::PositionsAara, true);
  EXPECT_EQ(codeOf([&] {
              encoded->put({1, 1, 1}, 1, models::Encoding::PositionsAara, big);
            }),
            ErrorCode::ResourceExhausted);
  // The registry lets go of the cache (the model closes) while a response still holds a body.
  encoded.reset();
  EXPECT_EQ(held->bytes().size(), big.size());
}

TEST(EncodedCache, OpenFilesAreBoundedByTheHandleBudget) {
  const DataRoot root;
  writeModel(root.path() / "m");
  core::PatchCache cache(64 * kMiB);
  cache.setHandleBudget(2);
  const auto live = core::LiveModel::open(root.path() / "m", "m", cache);
  const auto encoded = models::EncodedCache::create(cache, *live);
  const auto snapshot = live->snapshot();
  const auto open = [&](const core::PatchKey& key) {
    auto file = core::openFullGridPositions(live->dir(), kSize, snapshot->model->at(key));
    EXPECT_NE(file, nullptr) << key.toString();  // written whole
    return file;
  };
  auto first = encoded->putFile({2, 0, 0}, 1, models::StoredKind::Positions, open({2, 0, 0}));
  EXPECT_EQ(first->size(), 13u + kSize * kSize * 12u);
  char header[5] = {};
  ASSERT_EQ(::pread(first->fd(), header, 4, 0), 4);
  EXPECT_STREQ(header, "\x03V3f");
  encoded->putFile({2, 1, 0}, 1, models::StoredKind::Positions, open({2, 1, 0}));
  encoded->putFile({2, 2, 0}, 1, models::StoredKind::Positions, open({2, 2, 0}));
  EXPECT_EQ(cache.stats().handles, 2u);
  EXPECT_NE(encoded->findFile({2, 0, 0}, 1, models::StoredKind::Positions, true), nullptr);
  EXPECT_EQ(encoded->findFile({2, 1, 0}, 1, models::StoredKind::Positions, true), nullptr);
  // Both held (one by `first`, one by `third`): a further file is refused, so it is encoded.
  const auto third = encoded->findFile({2, 2, 0}, 1, models::StoredKind::Positions, true);
  EXPECT_EQ(codeOf([&] {
              encoded->putFile({2, 3, 0}, 1, models::StoredKind::Positions, open({2, 3, 0}));
            }),
            ErrorCode::ResourceExhausted);
}

TEST(EncodedCache, APublishDropsTheEntriesOfTheVersionsItReplaced) {
  const DataRoot root;
  writeModel(root.path() / "m");
  core::PatchCache cache(64 * kMiB);
  const auto live = core::LiveModel::open(root.path() / "m", "m", cache);
  const auto encoded = models::EncodedCache::create(cache, *live);
  const auto before = live->snapshot();
  const core::PatchKey leaf{2, 1, 2};
  const core::PatchKey other{2, 0, 0};
  for (const core::PatchKey& key : {core::PatchKey::root(), leaf, other}) {
    encoded->put(key, before->model->at(key).version, models::Encoding::Glb, bytesOf("x"));
  }
  {
    auto edit = live->beginEdit();
    edit->setPositions(leaf, leafGrid(1, 2));
    edit->publish();
  }
  // The leaf and its ancestors have new versions: their old entries are gone at once, while a
  // reader of the old snapshot still holds it; the untouched patch keeps its entry.
  EXPECT_EQ(encoded->find(leaf, before->model->at(leaf).version, models::Encoding::Glb, true),
            nullptr);
  EXPECT_EQ(encoded->find(core::PatchKey::root(), before->model->at(core::PatchKey::root()).version,
                          models::Encoding::Glb, true),
            nullptr);
  EXPECT_NE(encoded->find(other, before->model->at(other).version, models::Encoding::Glb, true),
            nullptr);
  EXPECT_EQ(
      cache.stats().residentByCategory[static_cast<std::size_t>(core::MemoryCategory::Encoded)],
      1u);
}

// ---- jobs ------------------------------------------------------------------------------------

/// A gate a test opens to let a job go on.
class Gate {
 public:
  void open() {
    {
      const std::lock_guard lock(mutex_);
      open_ = true;
    }
    cv_.notify_all();
  }
  void wait() {
    std::unique_lock lock(mutex_);
    cv_.wait(lock, [this] { return open_; });
  }

 private:
  std::mutex mutex_;
  std::condition_variable cv_;
  bool open_ = false;
};

jobs::JobStatus waitFinal(const jobs::JobRegistry& registry, const std::string& id) {
  const auto deadline = std::chrono::steady_clock::now() + 120s;  // only ends a hang
  for (;;) {
    jobs::JobStatus status = registry.get(id);
    if (jobs::isFinal(status.state) || std::chrono::steady_clock::now() > deadline) {
      return status;
    }
    std::this_thread::sleep_for(2ms);
  }
}

TEST(JobRegistry, RunsAJobAndMapsStagesOntoOneRisingFraction) {
  exec::WorkPool pool("jobs", 1);
  jobs::JobRegistry registry(pool);
  Gate halfway;
  Gate resume;
  const auto job = registry.submit(
      "test", {{"a", 1}}, {{"first", 1}, {"second", 3}}, [&](jobs::JobContext& context) {
        context.report("first", 1);
        context.report("second", 0.5);
        context.report("unplanned", 0.1);  // shown, but the fraction stays
        halfway.open();
        resume.wait();
        return json{{"answer", 42}};
      });
  EXPECT_EQ(job.state, jobs::JobState::Queued);
  halfway.wait();
  const jobs::JobStatus running = registry.get(job.id);
  EXPECT_EQ(running.state, jobs::JobState::Running);
  EXPECT_EQ(running.stage, "unplanned");
  EXPECT_DOUBLE_EQ(running.progress, 0.25 + 0.75 * 0.5);
  resume.open();
  const jobs::JobStatus done = waitFinal(registry, job.id);
  EXPECT_EQ(done.state, jobs::JobState::Succeeded);
  EXPECT_EQ(done.progress, 1);
  EXPECT_EQ(done.result, json({{"answer", 42}}));
  const json wire = jobs::toJson(done);
  EXPECT_EQ(wire.at("state"), "succeeded");
  EXPECT_TRUE(wire.at("error").is_null());
  EXPECT_TRUE(wire.at("finished_at").is_string());
  EXPECT_EQ(codeOf([&] { registry.cancel(job.id); }), ErrorCode::Conflict);
  EXPECT_EQ(codeOf([&] { registry.get("nope"); }), ErrorCode::NotFound);
  pool.join();
}

TEST(JobRegistry, CancelStopsQueuedJobsAtOnceAndRunningOnesAtTheirNextCheck) {
  exec::WorkPool pool("jobs", 1);
  jobs::JobRegistry registry(pool);
  Gate started;
  std::atomic<bool> secondRan{false};
  const auto first = registry.submit("test", json::object(), {}, [&](jobs::JobContext& context) {
    started.open();
    while (true) {
      context.throwIfCancelled();
      std::this_thread::sleep_for(1ms);
    }
    return json();
  });
  const auto second = registry.submit("test", json::object(), {}, [&](jobs::JobContext&) {
    secondRan = true;
    return json();
  });
  started.wait();
  const auto queued = registry.cancel(second.id);
  EXPECT_EQ(queued.state, jobs::JobState::Cancelled);
  const auto running = registry.cancel(first.id);
  EXPECT_EQ(running.state, jobs::JobState::Running);
  EXPECT_TRUE(running.cancelRequested);
  const auto done = waitFinal(registry, first.id);
  EXPECT_EQ(done.state, jobs::JobState::Cancelled);
  EXPECT_EQ(done.errorCode, ErrorCode::Cancelled);
  pool.join();
  EXPECT_FALSE(secondRan);
  EXPECT_EQ(registry.counts().at(jobs::JobState::Cancelled), 2u);
}

TEST(JobRegistry, FailuresKeepTheirCodeAndTheQueueIsBounded) {
  exec::WorkPool pool("jobs", 1);
  jobs::JobRegistry registry(pool, {.active = 2, .finished = 1, .node = {}});
  Gate gate;
  const auto failing = registry.submit("test", json::object(), {}, [&](jobs::JobContext&) -> json {
    gate.wait();
    throw Error(ErrorCode::InvalidArgument, "bad input");
  });
  const auto second =
      registry.submit("test", json::object(), {}, [](jobs::JobContext&) { return json::object(); });
  EXPECT_EQ(codeOf([&] {
              registry.submit("test", json::object(), {}, [](jobs::JobContext&) { return json(); });
            }),
            ErrorCode::Unavailable);
  gate.open();
  EXPECT_EQ(waitFinal(registry, second.id).state, jobs::JobState::Succeeded);
  // Only the newest finished job is remembered.
  EXPECT_EQ(codeOf([&] { registry.get(failing.id); }), ErrorCode::NotFound);
  registry.cancelAll();
  EXPECT_EQ(codeOf([&] {
              registry.submit("test", json::object(), {}, [](jobs::JobContext&) { return json(); });
            }),
            ErrorCode::Unavailable);
  pool.join();
}

TEST(JobRegistry, InAClusterJobIdsNameTheNodeAndALostLeaseCancelsButStillTakesJobs) {
  exec::WorkPool pool("jobs", 1);
  jobs::JobRegistry registry(pool, {.active = 4, .finished = 4, .node = "n2"});
  Gate gate;
  const auto running = registry.submit("test", json::object(), {}, [&](jobs::JobContext& context) {
    gate.wait();
    context.throwIfCancelled();
    return json::object();
  });
  EXPECT_TRUE(running.id.starts_with("n2-")) << running.id;
  registry.cancelAll(/*refuseNew=*/false);
  gate.open();
  EXPECT_EQ(waitFinal(registry, running.id).state, jobs::JobState::Cancelled);
  const auto next =
      registry.submit("test", json::object(), {}, [](jobs::JobContext&) { return json::object(); });
  EXPECT_EQ(waitFinal(registry, next.id).state, jobs::JobState::Succeeded);
  pool.join();
}

// ---- the patch-data service ------------------------------------------------------------------

/// The one rule of where a body is made: a network thread only looks (one miss counted, null), the
/// pool after it makes and puts without counting a second miss, and the next network-thread look
/// finds the very bytes; the pool alone (no look before) counts its miss.
TEST(PatchData, ANetworkThreadOnlyLooksAndThePoolMakesWithOneMissPerRequest) {
  const DataRoot root;
  writeModel(root.path() / "m");
  core::PatchCache cache(64 * kMiB);
  models::ModelRegistry registry(root.path(), cache);
  registry.openAll();
  const models::ModelRegistry::Served served = registry.getServed("m");
  const auto snapshot = served.live->snapshot();
  const core::PatchInfo& leaf = snapshot->model->at({2, 1, 1});
  models::PatchData data;
  const auto misses = [&] { return cache.stats().misses; };
  const auto glbBytes = [&] {
    const auto by = cache.stats().encodedByFormat;
    const auto it = by.find(static_cast<std::uint8_t>(models::Encoding::Glb));
    return it == by.end() ? std::size_t{0} : it->second;
  };

  std::uint64_t before = misses();
  EXPECT_EQ(
      data.glb(served, *snapshot, leaf, core::GlbCompression::None, models::Asker::NetworkThread),
      nullptr);
  EXPECT_EQ(misses(), before + 1);
  EXPECT_EQ(glbBytes(), 0u);
  const auto made = data.glb(served, *snapshot, leaf, core::GlbCompression::None,
                             models::Asker::PoolAfterNetwork);
  ASSERT_NE(made, nullptr);
  EXPECT_GT(made->bytes().size(), 0u);
  EXPECT_EQ(glbBytes(), made->bytes().size());
  before = misses();
  const auto found =
      data.glb(served, *snapshot, leaf, core::GlbCompression::None, models::Asker::NetworkThread);
  ASSERT_NE(found, nullptr);
  EXPECT_EQ(found->bytes().data(), made->bytes().data());  // the cached body, not a copy
  EXPECT_EQ(misses(), before);

  // Positions: one look at the open file and the encoding, one miss for both.
  before = misses();
  EXPECT_FALSE(data.positions(served, *snapshot, leaf, models::Asker::NetworkThread));
  EXPECT_EQ(misses(), before + 1);
  const auto positions = data.positions(served, *snapshot, leaf, models::Asker::PoolAfterNetwork);
  ASSERT_TRUE(positions);
  EXPECT_EQ(misses(), before + 1);
  EXPECT_TRUE(positions->file != nullptr || positions->body != nullptr);
  EXPECT_EQ(positions->local2global, models::matrixText(leaf.local2global));
  EXPECT_TRUE(data.positions(served, *snapshot, leaf, models::Asker::NetworkThread));

  // The pool with no look before counts its own miss, once.
  const core::PatchInfo& other = snapshot->model->at({2, 0, 0});
  before = misses();
  ASSERT_TRUE(data.positions(served, *snapshot, other, models::Asker::Pool));
  EXPECT_EQ(misses(), before + 1);
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
  jobs::JobRegistry jobs_{pool_};
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
