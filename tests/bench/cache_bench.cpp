// Benchmark (not a test): hit rate and throughput of the cache's eviction policies on the same
// skewed (Zipf) access trace over real models.
//
//   cache_bench <opc-dir>... [--budget-fraction F] [--accesses N] [--zipf S]
//
// Every patch of every model is one item; items are ranked in a random (seeded) order and drawn
// with probability ~ 1 / rank^S. The budget is F times the models' total vertex data. Both
// policies replay the identical trace on a fresh cache; page-cache effects are equalised by a
// warm-up pass that reads every patch once before either run.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/validate.hpp"
#include "core/store/live_model.hpp"

using namespace vsm::core;

namespace {

struct Item {
  std::size_t model;
  PatchKey key;
};

struct Result {
  double hitRate;
  double accessesPerSecond;
  CacheStats stats;
};

Result replay(const std::vector<std::string>& dirs, const std::vector<Item>& trace,
              std::size_t budget, EvictionPolicy policy) {
  PatchCache cache(budget, policy);
  std::vector<std::unique_ptr<LiveModel>> models;
  for (std::size_t i = 0; i < dirs.size(); ++i) {
    models.push_back(LiveModel::open(dirs[i], "m" + std::to_string(i), cache));
  }
  std::vector<std::shared_ptr<const ModelSnapshot>> snapshots;
  for (const auto& m : models) {
    snapshots.push_back(m->snapshot());
  }
  double checksum = 0;
  const auto start = std::chrono::steady_clock::now();
  for (const Item& item : trace) {
    const auto pin = models[item.model]->positions(*snapshots[item.model], item.key);
    checksum += pin.get<PatchGrid>()->positions()[0];
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  Result r{};
  r.stats = cache.stats();
  r.hitRate =
      static_cast<double>(r.stats.hits) / static_cast<double>(r.stats.hits + r.stats.misses);
  r.accessesPerSecond = static_cast<double>(trace.size()) / seconds;
  if (checksum == 12345.678) {
    std::puts("");  // keeps the reads from being optimised away
  }
  snapshots.clear();
  models.clear();
  return r;
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> dirs;
  double budgetFraction = 0.25;
  std::size_t accesses = 200000;
  double zipf = 1.0;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg == "--budget-fraction" && i + 1 < argc) {
      budgetFraction = std::stod(argv[++i]);
    } else if (arg == "--accesses" && i + 1 < argc) {
      accesses = std::stoul(argv[++i]);
    } else if (arg == "--zipf" && i + 1 < argc) {
      zipf = std::stod(argv[++i]);
    } else {
      dirs.push_back(arg);
    }
  }
  if (dirs.empty()) {
    std::fprintf(stderr,
                 "usage: cache_bench <opc-dir>... [--budget-fraction F] [--accesses N] "
                 "[--zipf S]\n");
    return 2;
  }
  try {
    std::vector<Item> items;
    std::size_t gridBytes = 0;
    for (std::size_t i = 0; i < dirs.size(); ++i) {
      const Model model = readOpcModel(dirs[i]);
      gridBytes = static_cast<std::size_t>(model.gridSize()) * model.gridSize() * 12;
      for (const auto& [key, info] : model.patches()) {
        items.push_back({i, key});
      }
    }
    const std::size_t total = items.size() * gridBytes;
    const auto budget = static_cast<std::size_t>(static_cast<double>(total) * budgetFraction);

    std::mt19937_64 rng(20261125);
    std::shuffle(items.begin(), items.end(), rng);
    std::vector<double> weights(items.size());
    for (std::size_t r = 0; r < items.size(); ++r) {
      weights[r] = 1.0 / std::pow(static_cast<double>(r + 1), zipf);
    }
    std::discrete_distribution<std::size_t> draw(weights.begin(), weights.end());
    std::vector<Item> trace;
    trace.reserve(accesses);
    for (std::size_t n = 0; n < accesses; ++n) {
      trace.push_back(items[draw(rng)]);
    }

    // Warm-up: every patch read once, so both runs find the files in the page cache.
    replay(dirs, items, total + gridBytes, EvictionPolicy::CostAwareClock);

    std::printf("models: %zu, patches: %zu, vertex data: %.1f MiB, budget: %.1f MiB (%.0f %%)\n",
                dirs.size(), items.size(), total / 1048576.0, budget / 1048576.0,
                budgetFraction * 100);
    std::printf("trace: %zu accesses, Zipf s = %.2f\n\n", accesses, zipf);
    std::printf("%-20s %9s %14s %10s %10s\n", "policy", "hit rate", "accesses/s", "misses",
                "evictions");
    Result results[2];
    const EvictionPolicy policies[2] = {EvictionPolicy::FifoSecondChance,
                                        EvictionPolicy::CostAwareClock};
    for (int p = 0; p < 2; ++p) {
      results[p] = replay(dirs, trace, budget, policies[p]);
      std::printf("%-20s %8.2f%% %14.0f %10llu %10llu\n",
                  std::string(toString(policies[p])).c_str(), results[p].hitRate * 100,
                  results[p].accessesPerSecond,
                  static_cast<unsigned long long>(results[p].stats.misses),
                  static_cast<unsigned long long>(results[p].stats.evictions));
    }
    std::printf(
        "\ndefault (cost-aware-clock) / baseline (fifo-second-chance): hit rate %.3fx, "
        "throughput %.3fx, misses %.3fx\n",
        results[1].hitRate / results[0].hitRate,
        results[1].accessesPerSecond / results[0].accessesPerSecond,
        static_cast<double>(results[1].stats.misses) /
            static_cast<double>(results[0].stats.misses));
  } catch (const Error& e) {
    std::fprintf(stderr, "cache_bench: %s\n", e.what());
    return 1;
  }
  return 0;
}
