#pragma once

// Helpers shared by the server modules' unit tests: a request as the reader makes it, bytes of a
// text, a synthetic model written as an OPC, a job's final status and a temporary data root.

#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <thread>
#include <utility>
#include <vector>

#include "core/grid/patch_grid.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/pyramid/model.hpp"
#include "server/http/message.hpp"
#include "server/jobs/job_registry.hpp"

namespace vsm::server::test {

namespace fs = std::filesystem;

inline constexpr int kSize = 17;  // 2^4 + 1
inline constexpr std::size_t kMiB = 1024 * 1024;

/// A request as the reader hands it to the pipeline (id "req-1"); a body is JSON.
inline http::Request request(http::Method method, std::string target, std::string body = {}) {
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

inline std::vector<std::byte> bytesOf(std::string_view text) {
  const auto span = std::as_bytes(std::span(text.data(), text.size()));
  return {span.begin(), span.end()};
}

/// Leaf (x, y) at depth 2 of a 4x4 bottom level on a 1 m lattice; leaf (3, 3) is left out.
inline std::shared_ptr<core::PatchGrid> leafGrid(std::uint32_t x, std::uint32_t y) {
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
inline void writeModel(const fs::path& dir) {
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
    core::PatchInfo& mutableInfo = model.edit(key);
    writer.writePatch(mutableInfo, *model.grid(key), model.childrenBox(key));
  }
  writer.writeHierarchy(model);
}

/// The status of job `id` once final (or after two minutes, which only ends a hang).
inline jobs::JobStatus waitFinal(const jobs::JobRegistry& registry, const std::string& id) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
  for (;;) {
    jobs::JobStatus status = registry.get(id);
    if (jobs::isFinal(status.state) || std::chrono::steady_clock::now() > deadline) {
      return status;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
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

}  // namespace vsm::server::test
