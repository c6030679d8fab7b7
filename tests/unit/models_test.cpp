// server/models: model ids and paths, the model registry, the encoded cache and the patch-data
// service, over a synthetic OPC in a temporary data root.
#include <gtest/gtest.h>

#include <unistd.h>

#include <chrono>
#include <cstring>
#include <filesystem>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/stored_file.hpp"
#include "core/store/live_model.hpp"
#include "core/store/model_edit.hpp"
#include "core/tiles/glb.hpp"
#include "core/tiles/tile_tree.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"
#include "server/models/patch_data.hpp"
#include "tests/unit/server_test_support.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::server {
namespace {

namespace fs = std::filesystem;
using core::Error;
using core::ErrorCode;
using core::test::codeOf;
using test::bytesOf;
using test::DataRoot;
using test::kMiB;
using test::kSize;
using test::leafGrid;
using test::writeModel;
using namespace std::chrono_literals;

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

TEST(ModelRegistry, AModelThatFailedToOpenWithAnIoErrorIsTriedAgainAtTheNextScan) {
  // A read error while the hierarchy stays the same (a disk's transient EIO; here a Patch.xml
  // that reads as a directory, EISDIR): the next openAll opens the model once it reads again,
  // though its hierarchy file did not change (a cluster node rescans every 500 ms).
  const DataRoot root;
  writeModel(root.path() / "m");
  const fs::path patchXml = root.path() / "m" / "Patches" / "0_0_0" / "Patch.xml";
  const fs::path aside = root.path() / "Patch.xml.aside";
  fs::rename(patchXml, aside);
  fs::create_directory(patchXml);
  core::PatchCache cache(64 * kMiB);
  models::ModelRegistry registry(root.path(), cache);
  EXPECT_EQ(codeOf([&] { core::readOpcModel(root.path() / "m"); }), ErrorCode::Io);
  EXPECT_EQ(registry.openAll(), 0u);
  EXPECT_EQ(registry.openAll(), 0u);
  fs::remove(patchXml);
  fs::rename(aside, patchXml);
  EXPECT_EQ(registry.openAll(), 1u);
  EXPECT_EQ(registry.get("m")->snapshot()->model->patchCount(), 20u);
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
  EXPECT_EQ(positions->local2global, models::matrixText(leaf.local2global()));
  EXPECT_TRUE(data.positions(served, *snapshot, leaf, models::Asker::NetworkThread));

  // The pool with no look before counts its own miss, once.
  const core::PatchInfo& other = snapshot->model->at({2, 0, 0});
  before = misses();
  ASSERT_TRUE(data.positions(served, *snapshot, other, models::Asker::Pool));
  EXPECT_EQ(misses(), before + 1);
}

/// The model root's tile tree is kept for its version and made for the next from it and the
/// change (the same as the full build); the version it replaced keeps its metadata alive until the
/// housekeeping's releaseRetired(), which frees it.
TEST(PatchData, ARootTileTreeFollowsTheChangeAndTheReplacedVersionGoesAtTheHousekeeping) {
  const DataRoot root;
  writeModel(root.path() / "m");
  core::PatchCache cache(64 * kMiB);
  models::ModelRegistry registry(root.path(), cache);
  registry.openAll();
  const models::ModelRegistry::Served served = registry.getServed("m");
  models::PatchData data;
  std::weak_ptr<const core::Model> first;
  {
    const auto snapshot = served.live->snapshot();
    first = snapshot->model;
    const auto tree = data.rootTileTree(served, *snapshot, 1);
    ASSERT_EQ(tree->children.size(), 4u);
    EXPECT_TRUE(tree->children[3].external);
    EXPECT_EQ(data.rootTileTree(served, *snapshot, 1), tree) << "kept for its version";
  }
  {
    // Leaf 2_3_2 (below 1_1_1) raised by 100 m.
    auto raised = leafGrid(3, 2);
    for (int j = 0; j < raised->size(); ++j) {
      for (int i = 0; i < raised->size(); ++i) {
        raised->setGlobal(i, j, raised->global(i, j) + core::Vec3d{0, 0, 100});
      }
    }
    auto edit = served.live->beginEdit();
    edit->setPositions({2, 3, 2}, raised);
    edit->publish();
  }
  const auto second = served.live->snapshot();
  const auto tree = data.rootTileTree(served, *second, 1);
  const core::TileNode full = core::buildTileTree(*second->model, core::PatchKey::root(), 1);
  ASSERT_EQ(tree->children.size(), full.children.size());
  for (std::size_t i = 0; i < full.children.size(); ++i) {
    EXPECT_EQ(tree->children[i].box.min, full.children[i].box.min) << i;
    EXPECT_EQ(tree->children[i].box.max, full.children[i].box.max) << i;
    EXPECT_EQ(tree->children[i].geometricError, full.children[i].geometricError) << i;
    EXPECT_EQ(tree->children[i].version, full.children[i].version) << i;
  }
  EXPECT_GT(full.children[3].box.max.z, 99.0) << "the raise shows in its external tile";
  EXPECT_FALSE(first.expired()) << "the replaced version waits for the housekeeping";
  data.releaseRetired();
  EXPECT_TRUE(first.expired()) << "and goes with it";
}

}  // namespace
}  // namespace vsm::server
