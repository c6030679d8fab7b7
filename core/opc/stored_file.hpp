#pragma once

#include <cstddef>
#include <filesystem>
#include <memory>
#include <optional>
#include <string_view>
#include <vector>

#include "core/pyramid/model.hpp"

namespace vsm::core {

/// A stored patch file open for reading (a read-only, close-on-exec descriptor) and its size, for
/// callers that send it as it is (sendfile(2)) rather than decode it. Closes the descriptor when
/// destroyed. The file is never written while open: published patch files are immutable (an edit
/// writes a new version into a new folder).
class StoredFile {
 public:
  StoredFile(int fd, std::size_t size) : fd_(fd), size_(size) {}
  ~StoredFile();
  StoredFile(const StoredFile&) = delete;
  StoredFile& operator=(const StoredFile&) = delete;

  int fd() const { return fd_; }
  std::size_t size() const { return size_; }

 private:
  int fd_;
  std::size_t size_;
};

/// The positions file of `info` (a patch of a model of gridSize x gridSize vertices stored at
/// `dir`), opened, when its bytes are exactly the full grid as `.aara`: the header of
/// encodeAaraHeader(V3f, {gridSize, gridSize}) followed by gridSize^2 float triples (nothing
/// cropped, float32). Only the header and the file's size are checked; undefined vertices are
/// NaN in the file as in a decoded grid (their payload bits may differ from a re-encoding's).
/// nullptr when the stored layout differs (a cropped rectangle, V3d): decode and re-encode then.
/// Throws Error(NotFound) for a missing file, Error(Unavailable) when the process is out of
/// descriptors, Error(Io) otherwise.
std::unique_ptr<StoredFile> openFullGridPositions(const std::filesystem::path& dir, int gridSize,
                                                  const PatchInfo& info);

/// The full-grid `.aara` of a patch stored cropped as V3f (what openFullGridPositions() does not
/// open): the header of encodeAaraHeader(V3f, {gridSize, gridSize}), then the grid's floats with
/// the stored rectangle's rows copied into place and every other vertex undefined; a vertex with
/// any NaN component becomes three quiet NaNs (as a decoded PatchGrid has them), so the bytes
/// equal those of the decoded grid's encoding, made without decoding. Its Local2Global is the
/// patch's. nullopt for a V3d file (decode and re-base it). Throws as openFullGridPositions(),
/// and Error(Corrupt) when the file does not hold the stored rectangle.
std::optional<std::vector<std::byte>> readFullGridPositions(const std::filesystem::path& dir,
                                                            int gridSize, const PatchInfo& info);

/// The whole of an open file (`what` names it in errors). Throws Error(Io) when it cannot be read
/// or is shorter than its size said.
std::vector<std::byte> readStoredFile(const StoredFile& file, std::string_view what);

/// The texture coordinates file of `info`, opened, after checking its header (V2f or V2d of the
/// stored rectangle's size) and its size. Throws Error(NotFound) when the patch has none or the
/// file is missing, Error(Corrupt) when it is not what the patch says, Error(Unavailable) when
/// the process is out of descriptors, Error(Io) otherwise.
std::unique_ptr<StoredFile> openCoordinatesFile(const std::filesystem::path& dir,
                                                const PatchInfo& info);

}  // namespace vsm::core
