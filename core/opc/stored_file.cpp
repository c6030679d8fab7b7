#include "core/opc/stored_file.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <cstring>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/opc_detail.hpp"
#include "core/opc/opc_store.hpp"

namespace fs = std::filesystem;

namespace vsm::core {

namespace {

/// A file of a patch folder as readers resolve it (either letter case).
fs::path patchFile(const fs::path& dir, const PatchInfo& info, const std::string& name) {
  const fs::path patchesDir = patchesDirOf(dir);
  const fs::path folderDir =
      detail::findEntry(patchesDir, info.folder).value_or(patchesDir / info.folder);
  return detail::findEntry(folderDir, name).value_or(folderDir / name);
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
  std::size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n =
        ::pread(file.fd(), bytes.data() + done, bytes.size() - done, static_cast<off_t>(done));
    if (n < 0 && errno == EINTR) {
      continue;
    }
    if (n < 0) {
      throwIoError("cannot read", what, errno);
    }
    if (n == 0) {
      break;
    }
    done += static_cast<std::size_t>(n);
  }
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
  const fs::path path = patchFile(dir, info, info.positionsFile);
  std::unique_ptr<StoredFile> file = openFile(path);
  if (file->size() != header.size() + n * n * elementSize(AaraType::V3f) ||
      readStart(*file, header.size(), path.string()) != header) {
    return nullptr;  // V3d, or another header
  }
  return file;
}

std::unique_ptr<StoredFile> openCoordinatesFile(const fs::path& dir, const PatchInfo& info) {
  if (info.coordinatesFile.empty()) {
    throw Error(ErrorCode::NotFound, "patch " + info.folder + " has no texture coordinates");
  }
  const fs::path path = patchFile(dir, info, info.coordinatesFile);
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
