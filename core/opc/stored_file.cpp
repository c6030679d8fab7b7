#include "core/opc/stored_file.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/opc_detail.hpp"
#include "core/opc/opc_reader.hpp"

namespace fs = std::filesystem;

namespace vsm::core {

namespace {

/// A file of a patch folder as readers resolve it (either letter case).
fs::path patchFile(const fs::path& dir, const PatchInfo& info, const std::string& name) {
  const fs::path patchesDir = patchesDirOf(dir);
  char buffer[PatchKey::kMaxText];
  return detail::entryPath(detail::entryPath(patchesDir, info.folder(buffer)), name);
}

std::unique_ptr<StoredFile> openFile(const fs::path& path) {
  const int fd = detail::openForReading(path);
  struct stat st {};
  if (::fstat(fd, &st) != 0) {
    const int errnum = errno;
    ::close(fd);
    throwIoError("cannot stat", path.string(), errnum);
  }
  return std::make_unique<StoredFile>(fd, static_cast<std::size_t>(st.st_size));
}

/// Up to `count` bytes from the start of the file (fewer when it is shorter).
std::vector<std::byte> readStart(const StoredFile& file, std::size_t count, std::string_view what) {
  std::vector<std::byte> bytes(std::min(count, file.size()));
  const std::size_t done = detail::readAt(file.fd(), 0, bytes, what);
  bytes.resize(done);
  return bytes;
}

}  // namespace

StoredFile::~StoredFile() {
  ::close(fd_);
}

std::vector<std::byte> readStoredFile(const StoredFile& file, std::string_view what) {
  std::vector<std::byte> bytes = readStart(file, file.size(), what);
  if (bytes.size() != file.size()) {
    throw Error(ErrorCode::Io, std::string(what) + ": shorter than its size");
  }
  return bytes;
}

std::unique_ptr<StoredFile> openFullGridPositions(const fs::path& dir, int gridSize,
                                                  const PatchInfo& info) {
  if (info.stored != GridRect{0, 0, gridSize, gridSize}) {
    return nullptr;  // cropped: the stored rectangle is not the grid the route serves
  }
  const std::array<std::int32_t, 2> sizes{gridSize, gridSize};
  const std::vector<std::byte> header = encodeAaraHeader(AaraType::V3f, sizes);
  const auto n = static_cast<std::size_t>(gridSize);
  const fs::path path = patchFile(dir, info, info.positionsFile());
  std::unique_ptr<StoredFile> file = openFile(path);
  if (file->size() != header.size() + n * n * elementSize(AaraType::V3f) ||
      readStart(*file, header.size(), path.string()) != header) {
    return nullptr;  // V3d, or another header
  }
  return file;
}

std::optional<std::vector<std::byte>> readFullGridPositions(const fs::path& dir, int gridSize,
                                                            const PatchInfo& info) {
  const fs::path path = patchFile(dir, info, info.positionsFile());
  const std::unique_ptr<StoredFile> file = openFile(path);
  const GridRect& r = info.stored;
  const std::array<std::int32_t, 2> storedSizes{r.width(), r.height()};
  const std::vector<std::byte> storedHeader = encodeAaraHeader(AaraType::V3f, storedSizes);
  const std::size_t rowBytes = static_cast<std::size_t>(r.width()) * 12;
  const std::vector<std::byte> bytes = readStoredFile(*file, path.string());
  if (bytes.size() < storedHeader.size() ||
      !std::equal(storedHeader.begin(), storedHeader.end(), bytes.begin())) {
    if (detail::decodeAaraHeader(bytes, path.string()).type == AaraType::V3d) {
      return std::nullopt;
    }
    throw Error(ErrorCode::Corrupt, path.string() + ": positions are not V3f of the stored " +
                                        std::to_string(r.width()) + " x " +
                                        std::to_string(r.height()));
  }
  if (bytes.size() != storedHeader.size() + rowBytes * static_cast<std::size_t>(r.height()) ||
      r.x0 < 0 || r.y0 < 0 || r.x1 > gridSize || r.y1 > gridSize) {
    throw Error(ErrorCode::Corrupt, path.string() + ": positions do not fit the stored rectangle");
  }
  const auto n = static_cast<std::size_t>(gridSize);
  const std::array<std::int32_t, 2> fullSizes{gridSize, gridSize};
  std::vector<std::byte> out = encodeAaraHeader(AaraType::V3f, fullSizes);
  const std::size_t header = out.size();
  // Every vertex undefined (three quiet NaNs), then the stored ones copied in. The floats follow
  // a 13-byte header, so they are written with memcpy (unaligned).
  out.resize(header + n * n * 12);
  const float nan = std::numeric_limits<float>::quiet_NaN();
  for (std::size_t i = 0; i < n * n * 3; ++i) {
    std::memcpy(out.data() + header + i * 4, &nan, 4);
  }
  for (int row = 0; row < r.height(); ++row) {
    const std::byte* from = bytes.data() + storedHeader.size() + rowBytes * row;
    std::byte* to = out.data() + header + (static_cast<std::size_t>(r.y0 + row) * n + r.x0) * 12;
    for (int x = 0; x < r.width(); ++x) {
      float v[3];
      std::memcpy(v, from + x * 12, 12);
      if (v[0] == v[0] && v[1] == v[1] && v[2] == v[2]) {
        std::memcpy(to + x * 12, v, 12);
      }
    }
  }
  return out;
}

std::unique_ptr<StoredFile> openCoordinatesFile(const fs::path& dir, const PatchInfo& info) {
  if (info.coordinatesFile().empty()) {
    throw Error(ErrorCode::NotFound, "patch " + info.folder() + " has no texture coordinates");
  }
  const fs::path path = patchFile(dir, info, info.coordinatesFile());
  std::unique_ptr<StoredFile> file = openFile(path);
  // The longest header of a 2-D array: a length byte, a type name of at most 6 letters, the
  // dimension count, two sizes.
  constexpr std::size_t kLongestHeader = 1 + 6 + 1 + 2 * 4;
  const std::vector<std::byte> start = readStart(*file, kLongestHeader, path.string());
  const detail::AaraHeader header = detail::decodeAaraHeader(start, path.string());
  const GridRect& r = info.stored;
  if ((header.type != AaraType::V2f && header.type != AaraType::V2d) || header.sizes.size() != 2 ||
      header.sizes[0] != r.width() || header.sizes[1] != r.height() ||
      header.headerBytes + header.dataBytes != file->size()) {
    throw Error(ErrorCode::Corrupt, path.string() +
                                        ": texture coordinates must be V2f or V2d of the stored "
                                        "positions' size " +
                                        std::to_string(r.width()) + " x " +
                                        std::to_string(r.height()));
  }
  return file;
}

}  // namespace vsm::core
