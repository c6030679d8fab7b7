#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <unordered_set>
#include <utility>
#include <vector>

#include "core/common/error.hpp"
#include "core/pyramid/model.hpp"
#include "core/pyramid/patch_key.hpp"
#include "core/pyramid/reduce.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::core {
namespace {

// A surface sampled on a global lattice: sample (u, v) at depth-independent spacing 1 m.
Vec3d surface(int u, int v) {
  return {1000.0 + u, 2000.0 + v, std::sin(u * 0.1) * 10 + v * 0.5};
}

// The child grid covering lattice samples [x0, x0 + size) x [y0, y0 + size).
std::shared_ptr<PatchGrid> sampled(int size, int x0, int y0) {
  auto grid = std::make_shared<PatchGrid>(size, Mat4d::translation({1000.0 + x0, 2000.0 + y0, 0}));
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      grid->setGlobal(x, y, surface(x0 + x, y0 + y));
    }
  }
  return grid;
}

TEST(PatchKey, ItsTextWrittenInPlaceIsItsString) {
  char text[PatchKey::kMaxText];
  EXPECT_EQ(PatchKey({3, 5, 2}).toChars(text), "3_5_2");
  for (const PatchKey key :
       {PatchKey::root(), PatchKey{10, 1023, 7}, PatchKey{30, 1073741823, 0}}) {
    EXPECT_EQ(key.toChars(text), key.toString());
    EXPECT_EQ(PatchKey::parse(key.toChars(text)), key);
  }
  // The longest a key can make (a damaged one's): within the room.
  const PatchKey widest{std::numeric_limits<int>::min(), 4294967295u, 4294967295u};
  EXPECT_EQ(widest.toChars(text), "-2147483648_4294967295_4294967295");
}

TEST(PatchKey, ParentOfRootIsEmpty) {
  EXPECT_FALSE(PatchKey::root().parent().has_value());
}

TEST(PatchKey, ChildAndParentAreInverse) {
  const PatchKey key{3, 5, 2};
  for (const Quadrant q : kQuadrants) {
    const PatchKey child = key.child(q);
    EXPECT_EQ(child.depth, 4);
    EXPECT_EQ(child.parent(), key);
    EXPECT_EQ(child.quadrant(), q);
    EXPECT_TRUE(key.isAncestorOrSelfOf(child));
  }
  EXPECT_EQ(key.child(Quadrant::SE), (PatchKey{4, 11, 5}));
  EXPECT_FALSE((PatchKey{4, 0, 0}).isAncestorOrSelfOf(key));
}

TEST(PatchKey, ToStringAndParseRoundTrip) {
  const PatchKey key{7, 100, 3};
  EXPECT_EQ(key.toString(), "7_100_3");
  EXPECT_EQ(PatchKey::parse("7_100_3"), key);
}

TEST(PatchKey, ParseRejectsEverythingElse) {
  for (const char* text : {"", "1_0", "1_0_0_0", "-1_0_0", "1_2_0", "01_0_0", "1_0_0 ", "../x",
                           "a_b_c", "31_0_0", "1__0"}) {
    EXPECT_FALSE(PatchKey::parse(text).has_value()) << text;
  }
}

TEST(Quadrant, NamesParseInEitherCase) {
  EXPECT_EQ(parseQuadrant("NW"), Quadrant::NW);
  EXPECT_EQ(parseQuadrant("se"), Quadrant::SE);
  EXPECT_FALSE(parseQuadrant("north").has_value());
}

TEST(Reduce, EveryParentVertexIsTheChildVertexAtTwiceItsIndex) {
  constexpr int kSize = 9;
  constexpr int kHalf = kSize - 1;
  std::array<std::shared_ptr<PatchGrid>, 4> children;
  std::array<const PatchGrid*, 4> pointers{};
  for (const Quadrant q : kQuadrants) {
    const int qi = static_cast<int>(q);
    children[qi] = sampled(kSize, (qi & 1) * kHalf, (qi >> 1) * kHalf);
    pointers[qi] = children[qi].get();
  }
  const PatchGrid parent = reduce(pointers);
  ASSERT_EQ(parent.size(), kSize);
  for (int j = 0; j < kSize; ++j) {
    for (int i = 0; i < kSize; ++i) {
      const Vec3d expected = surface(2 * i, 2 * j);
      const Vec3d got = parent.global(i, j);
      // The parent stores float32 locals around its own origin: equal within that rounding.
      EXPECT_NEAR(got.x, expected.x, 1e-4);
      EXPECT_NEAR(got.y, expected.y, 1e-4);
      EXPECT_NEAR(got.z, expected.z, 1e-4);
    }
  }
  EXPECT_NEAR(parent.resolution(), 2 * children[0]->resolution(), 0.2);
}

TEST(Reduce, AMissingChildLeavesItsAreaUndefinedButKeepsTheSharedBorder) {
  constexpr int kSize = 5;
  constexpr int kHalf = kSize - 1;
  auto nw = sampled(kSize, 0, 0);
  const PatchGrid parent = reduce({nw.get(), nullptr, nullptr, nullptr});
  for (int j = 0; j < kSize; ++j) {
    for (int i = 0; i < kSize; ++i) {
      const bool insideNw = 2 * i <= kHalf && 2 * j <= kHalf;
      EXPECT_EQ(parent.defined(i, j), insideNw) << i << "," << j;
    }
  }
}

TEST(Reduce, ABorderVertexComesFromTheFirstChildThatDefinesIt) {
  // NW and NE share their border column; where they disagree NW (the first quadrant) wins, and
  // where NW's vertex is undefined NE's is taken. Stored as translations (every grid vsm builds)
  // and with a rotation (the general path), the same globals.
  for (const bool rotated : {false, true}) {
    auto nw = sampled(5, 0, 0);
    auto ne = sampled(5, 4, 0);
    ne->setGlobal(0, 0, {7, 7, 7});  // disagrees with nw (4, 0)
    nw->setUndefined(4, 2);
    if (rotated) {
      Mat4d quarterTurn;  // x -> y, y -> -x, then nw's translation
      quarterTurn.m = {0, -1, 0, 1000, 1, 0, 0, 2000, 0, 0, 1, 0, 0, 0, 0, 1};
      auto turned = std::make_shared<PatchGrid>(5, quarterTurn);
      for (int y = 0; y < 5; ++y) {
        for (int x = 0; x < 5; ++x) {
          if (nw->defined(x, y)) {
            turned->setGlobal(x, y, nw->global(x, y));
          }
        }
      }
      nw = turned;
    }
    const PatchGrid parent = reduce({nw.get(), ne.get(), nullptr, nullptr});
    const auto near = [](const Vec3d& a, const Vec3d& b) {
      return std::abs(a.x - b.x) < 1e-3 && std::abs(a.y - b.y) < 1e-3 && std::abs(a.z - b.z) < 1e-3;
    };
    EXPECT_TRUE(near(parent.global(2, 0), surface(4, 0))) << rotated;
    EXPECT_TRUE(near(parent.global(2, 1), surface(4, 2))) << rotated;  // from NE
    EXPECT_TRUE(near(parent.global(4, 1), surface(8, 2))) << rotated;
    EXPECT_TRUE(near(parent.global(0, 2), surface(0, 4))) << rotated;
    EXPECT_FALSE(parent.defined(0, 3)) << rotated;  // below both
  }
}

TEST(Reduce, RejectsChildrenOfDifferentSizes) {
  auto a = sampled(5, 0, 0);
  auto b = sampled(9, 4, 0);
  EXPECT_THROW(reduce({a.get(), b.get(), nullptr, nullptr}), Error);
  EXPECT_THROW(reduce({nullptr, nullptr, nullptr, nullptr}), Error);
}

PatchInfo infoFor(const PatchKey& key) {
  PatchInfo info;
  info.key = key;
  return info;
}

TEST(Model, RejectsPatchSizesThatAreNotPowerOfTwoPlusOne) {
  EXPECT_THROW(Model(256), Error);
  EXPECT_THROW(Model(2), Error);
  // Sizes read from a damaged index: any int is refused without overflowing (fuzz opc_index).
  EXPECT_THROW(Model(std::numeric_limits<int>::min()), Error);
  EXPECT_THROW(Model(std::numeric_limits<int>::max()), Error);
  EXPECT_THROW(Model((1 << 16) + 1), Error);
  EXPECT_NO_THROW(Model((1 << 15) + 1));
  EXPECT_NO_THROW(Model(257));
  EXPECT_NO_THROW(Model(65));
}

TEST(Model, InsertNeedsTheParentAndSetsItsChildBit) {
  Model model(5);
  EXPECT_THROW(model.insert(infoFor({1, 0, 0})), Error);
  model.insert(infoFor(PatchKey::root()));
  model.insert(infoFor({1, 1, 0}));
  model.insert(infoFor({2, 3, 1}));
  EXPECT_TRUE(model.at(PatchKey::root()).hasChild(Quadrant::NE));
  EXPECT_FALSE(model.at(PatchKey::root()).hasChild(Quadrant::NW));
  EXPECT_EQ(model.children({1, 1, 0}), (std::vector<PatchKey>{{2, 3, 1}}));
  EXPECT_EQ(model.leaves(), (std::vector<PatchKey>{{2, 3, 1}}));
  EXPECT_EQ(model.maxDepth(), 2);
  EXPECT_THROW(model.insert(infoFor({1, 1, 0})), Error);
  EXPECT_THROW(model.at({1, 0, 0}), Error);
  EXPECT_EQ(model.find({1, 0, 0}), nullptr);
}

TEST(Model, VariableDepthSubPyramidsHaveLeavesOnSeveralLevels) {
  Model model(5);
  model.insert(infoFor(PatchKey::root()));
  for (const Quadrant q : kQuadrants) {
    model.insert(infoFor(PatchKey::root().child(q)));
  }
  model.insert(infoFor({2, 0, 0}));
  model.insert(infoFor({3, 1, 1}));
  const auto levels = model.levels();
  ASSERT_EQ(levels.size(), 4u);
  EXPECT_EQ(levels[1].leaves, 3u);
  EXPECT_EQ(levels[3].leaves, 1u);
  EXPECT_EQ(model.leaves().size(), 4u);
}

TEST(Model, ModelChangeListsAddedReplacedAndRemovedKeysAndComparesUnsharedNodesByField) {
  Model before(5);
  before.insert(infoFor(PatchKey::root()));
  for (const Quadrant q : kQuadrants) {
    before.insert(infoFor(PatchKey::root().child(q)));
  }
  before.insert(infoFor({2, 0, 0}));
  EXPECT_TRUE(modelChange(before, before).empty());

  // The same patches built again (no node shared): equal field by field, so no change; the
  // states (dirty, stale) are not the model's content.
  Model rebuilt(5);
  rebuilt.insert(infoFor(PatchKey::root()));
  for (const Quadrant q : kQuadrants) {
    rebuilt.insert(infoFor(PatchKey::root().child(q)));
  }
  rebuilt.insert(infoFor({2, 0, 0}));
  rebuilt.edit({1, 1, 1}).dirty = true;
  EXPECT_TRUE(modelChange(before, rebuilt).empty());

  // A copy that removes a leaf (its parent's child bit changes), adds one and replaces one.
  Model after = before;
  after.eraseLeaf({2, 0, 0});
  after.insert(infoFor({2, 3, 3}));
  after.edit({1, 1, 0}).version = 7;
  const ModelChange change = modelChange(before, after);
  EXPECT_EQ(change.changed, (std::vector<PatchKey>{{1, 0, 0}, {1, 1, 0}, {1, 1, 1}, {2, 3, 3}}));
  EXPECT_EQ(change.removed, (std::vector<PatchKey>{{2, 0, 0}}));
  const ModelChange back = modelChange(after, before);
  EXPECT_EQ(back.changed, (std::vector<PatchKey>{{1, 0, 0}, {1, 1, 0}, {1, 1, 1}, {2, 0, 0}}));
  EXPECT_EQ(back.removed, (std::vector<PatchKey>{{2, 3, 3}}));
}

// The model's keys and versions as a plain ordered map: the reference its chunked map is checked
// against.
using Reference = std::map<PatchKey, std::uint64_t>;

void expectModelMatches(const Model& model, const Reference& reference) {
  ASSERT_EQ(model.patchCount(), reference.size());
  auto expected = reference.begin();
  for (const auto& [key, info] : model.patches()) {
    ASSERT_EQ(key, expected->first);
    EXPECT_EQ(info.key, key);
    EXPECT_EQ(info.version, expected->second) << key.toString();
    std::uint8_t mask = 0;
    for (const Quadrant q : kQuadrants) {
      mask |= reference.count(key.child(q)) != 0 ? 1u << static_cast<int>(q) : 0u;
    }
    EXPECT_EQ(info.childMask, mask) << key.toString();
    ++expected;
  }
  auto backwards = reference.rbegin();
  for (const auto& [key, info] : model.patches().reversed()) {
    ASSERT_EQ(key, backwards->first);
    ++backwards;
  }
  EXPECT_EQ(backwards, reference.rend());
  EXPECT_EQ(model.maxDepth(), reference.rbegin()->first.depth);
}

TEST(Model, ThousandsOfInsertsErasesAndEditsOnCopiesMatchAPlainMapAndLeaveEarlierCopiesAsTheyWere) {
  // Enough patches for many chunks; inserts in the middle split chunks, erases empty and join
  // them, and copies taken along the way share chunks with the model changed after them.
  std::mt19937 random(31);
  Model model(5);
  Reference reference;
  const auto add = [&](const PatchKey& key) {
    model.insert(infoFor(key));
    reference[key] = 1;
  };
  add(PatchKey::root());
  for (int depth = 1; depth <= 5; ++depth) {
    for (std::uint32_t y = 0; y < (1u << depth); ++y) {
      for (std::uint32_t x = 0; x < (1u << depth); ++x) {
        add({depth, x, y});
      }
    }
  }
  expectModelMatches(model, reference);

  std::vector<std::pair<Model, Reference>> copies;
  for (int round = 0; round < 6; ++round) {
    copies.emplace_back(model, reference);
    for (int step = 0; step < 800; ++step) {
      auto it = reference.begin();
      std::advance(it, static_cast<std::ptrdiff_t>(random() % reference.size()));
      const PatchKey key = it->first;
      switch (random() % 3) {
        case 0:  // erase a leaf
          if (key.depth > 0 && model.at(key).isLeaf()) {
            model.eraseLeaf(key);
            reference.erase(key);
          }
          break;
        case 1: {  // a child that is not there yet
          const PatchKey child = key.child(kQuadrants[random() % 4]);
          if (key.depth < 8 && reference.count(child) == 0) {
            add(child);
          }
          break;
        }
        default:
          model.edit(key).version = ++it->second;
      }
    }
    expectModelMatches(model, reference);
  }
  for (const auto& [copy, held] : copies) {
    expectModelMatches(copy, held);
    // The change from the copy to the model, against the plain maps' difference.
    ModelChange expected;
    for (const auto& [key, version] : reference) {
      const auto before = held.find(key);
      if (before == held.end() || before->second != version ||
          copy.at(key).childMask != model.at(key).childMask) {
        expected.changed.push_back(key);
      }
    }
    for (const auto& [key, version] : held) {
      if (reference.count(key) == 0) {
        expected.removed.push_back(key);
      }
    }
    const ModelChange change = modelChange(copy, model);
    EXPECT_EQ(change.changed, expected.changed);
    EXPECT_EQ(change.removed, expected.removed);
  }
}

// levels() keeps each shared chunk's sums (a publish at 10^6 patches summed 1.4 million nodes
// twice): its answer must not depend on which chunks hold the patches, nor go stale when a chunk
// is changed after its sums were kept.
TEST(Model, LevelsAreTheMeanOfWholeNanometresWhicheverChunksHoldThePatches) {
  std::mt19937 random(7);
  std::uniform_real_distribution<double> metres(0.01, 100.0);
  Model model(5);
  const auto add = [&](const PatchKey& key) {
    PatchInfo info = infoFor(key);
    info.resolution = metres(random);
    const double x = key.x, y = key.y;
    info.globalBox = {{x, y, -static_cast<double>(key.depth)}, {x + 1, y + 1, metres(random)}};
    model.insert(std::move(info));
  };
  add(PatchKey::root());
  for (int depth = 1; depth <= 5; ++depth) {
    for (std::uint32_t y = 0; y < (1u << depth); ++y) {
      for (std::uint32_t x = 0; x < (1u << depth); ++x) {
        add({depth, x, y});
      }
    }
  }
  // What levels() must say, from the definition: per depth, counts, the union of the boxes and
  // the mean of the resolutions each rounded to whole nanometres (these sums fit 64 bits).
  const auto expectLevelsOf = [](const Model& m, const std::string& when) {
    std::map<int, LevelSummary> expected;
    std::map<int, std::pair<std::int64_t, std::size_t>> sums;
    for (const auto& [key, info] : m.patches()) {
      LevelSummary& level = expected[key.depth];
      level.depth = key.depth;
      ++level.patches;
      level.leaves += info.isLeaf() ? 1 : 0;
      level.bounds.extend(info.globalBox);
      if (info.resolution > 0) {
        sums[key.depth].first += std::llround(info.resolution * 1e9);
        ++sums[key.depth].second;
        if (info.isLeaf() && (level.finestLeaf == 0 || info.resolution < level.finestLeaf)) {
          level.finestLeaf = info.resolution;
        }
      }
    }
    const std::vector<LevelSummary> levels = m.levels();
    ASSERT_EQ(levels.size(), expected.size()) << when;
    for (const LevelSummary& level : levels) {
      const LevelSummary& want = expected.at(level.depth);
      const auto [nanometres, measured] = sums[level.depth];
      EXPECT_EQ(level.patches, want.patches) << when << " depth " << level.depth;
      EXPECT_EQ(level.leaves, want.leaves) << when << " depth " << level.depth;
      EXPECT_EQ(level.bounds, want.bounds) << when << " depth " << level.depth;
      EXPECT_EQ(level.finestLeaf, want.finestLeaf) << when << " depth " << level.depth;
      EXPECT_EQ(level.resolution, measured == 0 ? 0.0
                                                : static_cast<double>(nanometres) /
                                                      static_cast<double>(measured) * 1e-9)
          << when << " depth " << level.depth;
    }
  };
  expectLevelsOf(model, "built");
  std::vector<Model> copies;
  for (int round = 0; round < 8; ++round) {
    copies.push_back(model);  // shares every chunk: levels() keeps their sums
    expectLevelsOf(model, "shared, round " + std::to_string(round));
    if (round % 3 == 2) {
      copies.clear();  // the chunks are the model's alone again, their sums still kept
    }
    for (int step = 0; step < 300; ++step) {
      const std::uint32_t side = 1u << 5;
      const PatchKey key{5, static_cast<std::uint32_t>(random() % side),
                         static_cast<std::uint32_t>(random() % side)};
      switch (random() % 3) {
        case 0:
          if (model.find(key) != nullptr) {
            model.eraseLeaf(key);
          }
          break;
        case 1:
          if (model.find(key) == nullptr) {
            add(key);
          }
          break;
        default:
          if (model.find(key) != nullptr) {
            model.edit(key).resolution = metres(random);
            model.edit(*key.parent()).globalBox.max.z = metres(random);
          }
      }
    }
    expectLevelsOf(model, "changed, round " + std::to_string(round));
  }
  for (const Model& copy : copies) {
    expectLevelsOf(copy, "an earlier copy");
  }
  // The same patches inserted afresh sit in other chunks: the same levels, to the last bit.
  Model fresh(5);
  for (const auto& [key, info] : model.patches()) {
    PatchInfo same = info;
    same.childMask = 0;
    fresh.insert(std::move(same));
  }
  const std::vector<LevelSummary> a = model.levels(), b = fresh.levels();
  ASSERT_EQ(a.size(), b.size());
  for (std::size_t d = 0; d < a.size(); ++d) {
    EXPECT_EQ(a[d].resolution, b[d].resolution) << d;
    EXPECT_EQ(a[d].leaves, b[d].leaves) << d;
  }
}

// What vsmd charges to the budget for a model's metadata (issue 31): each version's tree, chunks
// shared between versions counted once.
TEST(Model, HeapBytesCountEveryNodeAndEachSharedChunkOnce) {
  Model model(5);
  model.insert(infoFor(PatchKey::root()));
  for (int depth = 1; depth <= 5; ++depth) {
    for (std::uint32_t y = 0; y < (1u << depth); ++y) {
      for (std::uint32_t x = 0; x < (1u << depth); ++x) {
        model.insert(infoFor({depth, x, y}));
      }
    }
  }
  std::unordered_set<const void*> counted;
  const std::size_t whole = model.heapBytes(counted);
  EXPECT_GE(whole, model.patchCount() * sizeof(PatchInfo));
  EXPECT_LE(whole, model.patchCount() * (sizeof(PatchInfo) + 160));
  // A copy shares every chunk: only its own vector of them is new.
  Model copy = model;
  EXPECT_LE(copy.heapBytes(counted), 64 * sizeof(void*));
  // A change copies one chunk (its nodes counted again: an upper estimate) and the node's name.
  copy.edit({5, 3, 3}).setFolder(std::string(100, 'f'));
  const std::size_t changed = copy.heapBytes(counted);
  EXPECT_GE(changed, sizeof(PatchInfo) + 100);
  EXPECT_LE(changed, whole / 4);
  // Counted afresh, the copy is an unchanged copy plus the name.
  std::unordered_set<const void*> alone, unchanged;
  EXPECT_GE(copy.heapBytes(alone), Model(model).heapBytes(unchanged) + 100);
}

// A model of 10^6 patches holds 1.4 million descriptions: each keeps Local2Global as its
// translation, its folder as its key and the usual file names as nothing at all, and gives back
// exactly what was set.
TEST(PatchInfo, KeepsWhatWasSetInLessRoom) {
  EXPECT_LE(sizeof(PatchInfo), 168u);
  PatchInfo info;
  info.key = {10, 123, 456};
  EXPECT_EQ(info.folder(), "10_123_456");
  EXPECT_FALSE(info.ownFolder());
  EXPECT_EQ(info.local2global(), Mat4d::identity());
  EXPECT_EQ(info.files(), PatchFiles{});
  EXPECT_EQ(info.ownHeapBytes(), 0u);

  const Mat4d shift = Mat4d::translation({6.4e6, -1.5e5, 3.25e6});
  info.setLocal2Global(shift);
  EXPECT_EQ(info.local2global(), shift);
  EXPECT_EQ(info.ownHeapBytes(), 0u);
  Mat4d general = shift;
  general.m[1] = 0.25;
  general.m[8] = -1e-9;
  info.setLocal2Global(general);
  EXPECT_EQ(info.local2global(), general);
  EXPECT_GT(info.ownHeapBytes(), sizeof(Mat4d));
  // Bit for bit: a -0 in the linear part is not a translation's +0 (it is written back as read).
  Mat4d negativeZero = shift;
  negativeZero.m[4] = -0.0;
  info.setLocal2Global(negativeZero);
  EXPECT_TRUE(std::signbit(info.local2global().m[4]));
  info.setLocal2Global(shift);
  EXPECT_EQ(info.ownHeapBytes(), 0u);

  const PatchFiles textured{"Positions.aara", "Coordinates.aara", "Diffuse\\10_123_456.tif"};
  info.setFiles(textured);
  EXPECT_EQ(info.files(), textured);
  EXPECT_EQ(info.textureFile(), "Diffuse\\10_123_456.tif");
  EXPECT_GT(info.ownHeapBytes(), sizeof(PatchFiles));
  PatchInfo copy = info;  // shares the names
  info.setFiles({"positions.AARA", "", ""});
  EXPECT_EQ(info.positionsFile(), "positions.AARA");
  EXPECT_TRUE(info.textureFile().empty());
  EXPECT_EQ(copy.files(), textured);
  info.setFiles({});
  EXPECT_EQ(info.ownHeapBytes(), 0u);

  // An edit's draft folder (or a foreign name) is kept, beside a matrix; the key's own is not.
  info.setFolder("10_123_456-v7-0badc0de");
  EXPECT_EQ(info.folder(), "10_123_456-v7-0badc0de");
  EXPECT_TRUE(info.ownFolder());
  EXPECT_GT(info.ownHeapBytes(), 0u);
  info.setLocal2Global(general);
  copy = info;
  info.setFolder("10_123_456");
  EXPECT_FALSE(info.ownFolder());
  EXPECT_EQ(info.folder(), "10_123_456");
  EXPECT_EQ(info.local2global(), general);
  EXPECT_EQ(copy.folder(), "10_123_456-v7-0badc0de");
  info.setLocal2Global(shift);
  EXPECT_EQ(info.ownHeapBytes(), 0u);
  EXPECT_EQ(copy.local2global(), general);

  // The stored rectangle in 8 bytes: any grid's (up to 2^15 + 1 a side), nothing past 16 bits.
  info.stored = GridRect{0, 1, 32769, 32768};
  EXPECT_EQ(static_cast<GridRect>(info.stored), (GridRect{0, 1, 32769, 32768}));
  EXPECT_EQ(info.stored.width(), 32769);
  EXPECT_THROW(info.stored = GridRect({-1, 0, 5, 5}), Error);
  EXPECT_THROW(info.stored = GridRect({0, 0, 65536, 5}), Error);
  EXPECT_EQ(info.stored.x1, 32769);
}

TEST(Model, ACopySharesEveryChunkItsChangeDidNotTouch) {
  Model model(5);
  for (int depth = 0; depth <= 5; ++depth) {  // 1,365 patches
    for (std::uint32_t y = 0; y < (1u << depth); ++y) {
      for (std::uint32_t x = 0; x < (1u << depth); ++x) {
        model.insert(infoFor({depth, x, y}));
      }
    }
  }
  Model copy = model;
  const PatchKey edited{5, 17, 9};
  copy.edit(edited).version = 2;
  const std::size_t touched = test::patchesInChunksOf(model, {edited});
  EXPECT_GT(touched, 1u);
  EXPECT_LE(touched, 256u);
  EXPECT_EQ(test::sharedPatches(model, copy), model.patchCount() - touched);
  // Held, a patch's chunk stays as it was: the next change copies it (again).
  const std::shared_ptr<const PatchInfo> held = copy.shared(edited);
  copy.edit(edited).version = 3;
  EXPECT_EQ(held->version, 2u);
  EXPECT_EQ(copy.at(edited).version, 3u);
  EXPECT_EQ(model.at(edited).version, 1u);
  EXPECT_EQ(modelChange(model, copy).changed, (std::vector<PatchKey>{edited}));
}

TEST(Model, ChangingAPatchMarksItDirtyAndEveryAncestorStale) {
  Model model(5);
  model.insert(infoFor(PatchKey::root()));
  model.insert(infoFor({1, 0, 0}));
  model.insert(infoFor({1, 1, 0}));
  model.insert(infoFor({2, 1, 1}));
  model.markChanged({2, 1, 1});
  EXPECT_TRUE(model.at({2, 1, 1}).dirty);
  EXPECT_TRUE(model.at({1, 0, 0}).stale);
  EXPECT_TRUE(model.at(PatchKey::root()).stale);
  EXPECT_FALSE(model.at({1, 1, 0}).stale);
  EXPECT_FALSE(model.at({1, 1, 0}).dirty);
}

TEST(Model, RefreshStaleRecomputesOverviewsBottomUpFromChangedChildren) {
  constexpr int kSize = 5;
  Model model(kSize);
  model.insert(infoFor(PatchKey::root()));
  model.insert(infoFor({1, 0, 0}));
  model.insert(infoFor({2, 0, 0}));
  model.insert(infoFor({2, 1, 1}));
  model.setGrid({2, 0, 0}, sampled(kSize, 0, 0));
  model.setGrid({2, 1, 1}, sampled(kSize, 4, 4));
  int loads = 0;
  model.refreshStale([&](const PatchInfo&) -> std::shared_ptr<const PatchGrid> {
    ++loads;
    return nullptr;
  });
  EXPECT_EQ(loads, 0);  // everything needed was resident
  const PatchInfo& mid = model.at({1, 0, 0});
  const PatchInfo& root = model.at(PatchKey::root());
  ASSERT_NE(model.grid({1, 0, 0}), nullptr);
  ASSERT_NE(model.grid(PatchKey::root()), nullptr);
  EXPECT_FALSE(mid.stale);
  EXPECT_FALSE(root.stale);
  EXPECT_TRUE(root.dirty);
  // Mid (depth 1) keeps every second lattice sample of its 9x9 union; root every fourth.
  EXPECT_NEAR(model.grid({1, 0, 0})->global(2, 2).z, surface(4, 4).z, 1e-4);
  EXPECT_NEAR(model.grid(PatchKey::root())->global(1, 1).z, surface(4, 4).z, 1e-4);
  EXPECT_NEAR(model.grid(PatchKey::root())->global(0, 0).z, surface(0, 0).z, 1e-4);
  EXPECT_TRUE(root.globalBox.contains(mid.globalBox, 1e-3));
}

TEST(Model, LeavesWhereDescendsOnlyThroughBoxesItAccepts) {
  constexpr int kSize = 5;
  Model model(kSize);
  model.insert(infoFor(PatchKey::root()));
  model.insert(infoFor({1, 0, 0}));
  model.insert(infoFor({1, 1, 1}));
  model.insert(infoFor({2, 0, 0}));
  model.insert(infoFor({2, 1, 1}));
  model.setGrid({2, 0, 0}, sampled(kSize, 0, 0));    // x 1000..1004, y 2000..2004
  model.setGrid({2, 1, 1}, sampled(kSize, 4, 4));    // x 1004..1008
  model.setGrid({1, 1, 1}, sampled(kSize, 10, 10));  // x 1010..1014
  model.refreshStale([](const PatchInfo&) { return nullptr; });
  const auto meeting = [&](double x0, double x1) {
    std::vector<Box3d> asked;
    const auto leaves = model.leavesWhere([&](const Box3d& b) {
      asked.push_back(b);
      return b.max.x >= x0 && b.min.x <= x1;
    });
    return std::pair{leaves, asked.size()};
  };
  EXPECT_EQ(meeting(-1e9, 1e9).first,
            (std::vector<PatchKey>{{1, 1, 1}, {2, 0, 0}, {2, 1, 1}}));  // in key order
  EXPECT_EQ(meeting(1010.5, 1011).first, (std::vector<PatchKey>{{1, 1, 1}}));
  // The root, its two children, and nothing below 1_0_0, whose box the range misses.
  EXPECT_EQ(meeting(1010.5, 1011).second, 3u);
  EXPECT_EQ(meeting(1005, 1006).first, (std::vector<PatchKey>{{2, 1, 1}}));
  EXPECT_TRUE(meeting(2000, 2001).first.empty());
  EXPECT_EQ(meeting(2000, 2001).second, 1u);
}

TEST(Model, AvgGeometrySizesRunFinestFirst) {
  constexpr int kSize = 5;
  Model model(kSize);
  model.insert(infoFor(PatchKey::root()));
  model.insert(infoFor({1, 0, 0}));
  model.setGrid({1, 0, 0}, sampled(kSize, 0, 0));
  model.refreshStale([](const PatchInfo&) { return nullptr; });
  const auto sizes = model.avgGeometrySizes();
  ASSERT_EQ(sizes.size(), 2u);
  EXPECT_LT(sizes[0], sizes[1]);
  EXPECT_NEAR(sizes[0], model.at({1, 0, 0}).resolution, 1e-9);
}

}  // namespace
}  // namespace vsm::core
