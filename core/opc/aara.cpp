#include "core/opc/aara.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstring>
#include <limits>
#include <string>

#include "core/common/error.hpp"
#include "core/opc/opc_detail.hpp"

namespace vsm::core {
namespace {

struct TypeEntry {
  AaraType type;
  std::string_view name;
  std::size_t size;
};

// Names and element sizes exactly as OPC.md lists them.
constexpr std::array<TypeEntry, 12> kTypes{{
    {AaraType::Byte, "byte", 1},
    {AaraType::Int, "int", 4},
    {AaraType::Float, "float", 4},
    {AaraType::Double, "double", 8},
    {AaraType::V2f, "V2f", 8},
    {AaraType::V3f, "V3f", 12},
    {AaraType::V2d, "V2d", 16},
    {AaraType::V3d, "V3d", 24},
    {AaraType::C3b, "C3b", 3},
    {AaraType::C4b, "C4b", 4},
    {AaraType::C3f, "C3f", 12},
    {AaraType::C4f, "C4f", 16},
}};

const TypeEntry& entryOf(AaraType type) {
  for (const TypeEntry& entry : kTypes) {
    if (entry.type == type) {
      return entry;
    }
  }
  throw Error(ErrorCode::Internal, "unknown AaraType");
}

[[noreturn]] void corrupt(std::string_view what, const std::string& message) {
  throw Error(ErrorCode::Corrupt, std::string(what) + ": " + message);
}

// Explicit little-endian decoding, independent of the host's byte order.
std::int32_t readInt32Le(const std::byte* p) {
  const std::uint32_t u =
      std::to_integer<std::uint32_t>(p[0]) | std::to_integer<std::uint32_t>(p[1]) << 8 |
      std::to_integer<std::uint32_t>(p[2]) << 16 | std::to_integer<std::uint32_t>(p[3]) << 24;
  return static_cast<std::int32_t>(u);
}

void appendInt32Le(std::vector<std::byte>& out, std::int32_t value) {
  const auto u = static_cast<std::uint32_t>(value);
  for (int shift = 0; shift < 32; shift += 8) {
    out.push_back(static_cast<std::byte>((u >> shift) & 0xFF));
  }
}

/// Element count of `sizes`; nullopt on a negative size or when count x elementSize (plus a
/// header) would not fit in size_t.
std::optional<std::size_t> checkedCount(std::span<const std::int32_t> sizes,
                                        std::size_t elementBytes) {
  std::size_t count = 1;
  // Leave room for the header so header + count * elementBytes cannot overflow either.
  const std::size_t limit = (std::numeric_limits<std::size_t>::max() - 1024) / elementBytes;
  for (const std::int32_t size : sizes) {
    if (size < 0) {
      return std::nullopt;
    }
    const auto s = static_cast<std::size_t>(size);
    if (s != 0 && count > limit / s) {
      return std::nullopt;
    }
    count *= s;
  }
  return count;
}

/// The longest header: name length, a 127-byte name, dimension count, 4 sizes.
constexpr std::size_t kMaxHeaderBytes = 1 + 127 + 1 + 4 * 4;

/// Throws Error(Corrupt) unless `length` bytes are exactly the header and its data.
void checkLength(const detail::AaraHeader& header, std::size_t length, std::string_view what) {
  const std::size_t expected = header.headerBytes + header.dataBytes;
  if (length < expected) {
    corrupt(what, "truncated .aara data: " + std::to_string(length) + " bytes instead of " +
                      std::to_string(expected));
  }
  if (length > expected) {
    corrupt(what, std::to_string(length - expected) + " trailing bytes after the .aara data");
  }
}

}  // namespace

std::string_view toString(AaraType type) {
  return entryOf(type).name;
}

std::optional<AaraType> parseAaraType(std::string_view name) {
  for (const TypeEntry& entry : kTypes) {
    if (entry.name == name) {
      return entry.type;
    }
  }
  return std::nullopt;
}

std::size_t elementSize(AaraType type) {
  return entryOf(type).size;
}

std::size_t AaraArray::elementCount() const {
  std::size_t count = 1;
  for (const std::int32_t size : sizes) {
    count *= size < 0 ? 0 : static_cast<std::size_t>(size);
  }
  return count;
}

namespace detail {

std::size_t readAt(int fd, std::size_t offset, std::span<std::byte> out, std::string_view what) {
  std::size_t done = 0;
  while (done < out.size()) {
    const ssize_t n =
        ::pread(fd, out.data() + done, out.size() - done, static_cast<off_t>(offset + done));
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
  return done;
}

int openForReading(const std::filesystem::path& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    const int errnum = errno;
    if (errnum == ENOENT || errnum == ENOTDIR) {
      throw Error(ErrorCode::NotFound, "no file '" + path.string() + "'");
    }
    throwIoError("cannot open", path.string(), errnum);
  }
  return fd;
}

std::vector<std::byte> readFile(const std::filesystem::path& path, std::size_t maxBytes) {
  const int fd = openForReading(path);
  struct stat st {};
  const std::size_t expected =
      ::fstat(fd, &st) == 0 && st.st_size > 0 ? static_cast<std::size_t>(st.st_size) : 0;
  // One read for a file whose size fstat told us; grows when it is longer than that.
  std::vector<std::byte> bytes(std::min(maxBytes, std::max<std::size_t>(expected, 4096)));
  std::size_t used = 0;
  while (used < maxBytes) {
    if (used == bytes.size()) {
      bytes.resize(std::min(maxBytes, bytes.size() * 2));
    }
    const ssize_t got = ::read(fd, bytes.data() + used, bytes.size() - used);
    if (got < 0) {
      if (errno == EINTR) {
        continue;
      }
      const int errnum = errno;
      ::close(fd);
      throwIoError("cannot read", path.string(), errnum);
    }
    if (got == 0) {
      break;
    }
    used += static_cast<std::size_t>(got);
  }
  bytes.resize(used);
  ::close(fd);
  return bytes;
}

AaraHeader decodeAaraHeader(std::span<const std::byte> bytes, std::string_view what) {
  if (bytes.empty()) {
    corrupt(what, "truncated .aara header (empty file)");
  }
  const std::size_t nameLength = std::to_integer<std::size_t>(bytes[0]);
  if (nameLength >= 128) {
    corrupt(what, "bad .aara header: type name length " + std::to_string(nameLength));
  }
  if (bytes.size() < 1 + nameLength + 1) {
    corrupt(what, "truncated .aara header");
  }
  std::string name(nameLength, '\0');
  std::memcpy(name.data(), bytes.data() + 1, nameLength);
  const auto type = parseAaraType(name);
  if (!type) {
    std::string printable;
    for (const char c : name) {
      printable += (c >= 0x20 && c < 0x7F) ? c : '?';
    }
    corrupt(what, "unknown .aara element type '" + printable + "'");
  }
  const std::size_t dims = std::to_integer<std::size_t>(bytes[1 + nameLength]);
  if (dims < 1 || dims > 4) {
    corrupt(what, ".aara dimension count " + std::to_string(dims) + " is outside 1..4");
  }
  const std::size_t headerBytes = 1 + nameLength + 1 + 4 * dims;
  if (bytes.size() < headerBytes) {
    corrupt(what, "truncated .aara header");
  }
  AaraHeader header;
  header.type = *type;
  header.headerBytes = headerBytes;
  for (std::size_t d = 0; d < dims; ++d) {
    header.sizes.push_back(readInt32Le(bytes.data() + 1 + nameLength + 1 + 4 * d));
  }
  const std::size_t elementBytes = elementSize(*type);
  const auto count = checkedCount(header.sizes, elementBytes);
  if (!count) {
    std::string sizes;
    for (const std::int32_t s : header.sizes) {
      sizes += (sizes.empty() ? "" : " x ") + std::to_string(s);
    }
    corrupt(what, "bad .aara sizes " + sizes + " (negative or too large)");
  }
  header.dataBytes = *count * elementBytes;
  return header;
}

AaraHeader readAaraHeader(const std::filesystem::path& path) {
  const std::vector<std::byte> bytes = readFile(path, kMaxHeaderBytes);
  return decodeAaraHeader(bytes, path.string());
}

}  // namespace detail

AaraArray decodeAara(std::span<const std::byte> bytes, std::string_view what) {
  const detail::AaraHeader header = detail::decodeAaraHeader(bytes, what);
  checkLength(header, bytes.size(), what);
  AaraArray array;
  array.type = header.type;
  array.sizes = header.sizes;
  array.data.assign(bytes.begin() + static_cast<std::ptrdiff_t>(header.headerBytes), bytes.end());
  return array;
}

std::vector<std::byte> encodeAaraHeader(AaraType type, std::span<const std::int32_t> sizes) {
  if (sizes.empty() || sizes.size() > 4) {
    throw Error(ErrorCode::InvalidArgument,
                "an .aara array needs 1..4 dimensions, not " + std::to_string(sizes.size()));
  }
  if (!checkedCount(sizes, elementSize(type))) {
    throw Error(ErrorCode::InvalidArgument, ".aara sizes are negative or too large");
  }
  const std::string_view name = toString(type);
  std::vector<std::byte> out;
  out.push_back(static_cast<std::byte>(name.size()));
  for (const char c : name) {
    out.push_back(static_cast<std::byte>(c));
  }
  out.push_back(static_cast<std::byte>(sizes.size()));
  for (const std::int32_t size : sizes) {
    appendInt32Le(out, size);
  }
  return out;
}

std::vector<std::byte> encodeAara(const AaraArray& array) {
  std::vector<std::byte> out = encodeAaraHeader(array.type, array.sizes);
  const auto count = checkedCount(array.sizes, elementSize(array.type));
  if (!count || *count * elementSize(array.type) != array.data.size()) {
    throw Error(ErrorCode::InvalidArgument, ".aara data size does not match its type and sizes");
  }
  out.insert(out.end(), array.data.begin(), array.data.end());
  return out;
}

AaraArray readAaraFile(const std::filesystem::path& path) {
  // The header is checked against the file's length before the data is allocated: a header can
  // claim anything up to 2^31 x 2^31 elements, the file cannot.
  const std::string what = path.string();
  const int fd = detail::openForReading(path);
  struct Closer {
    int fd;
    ~Closer() { ::close(fd); }
  } closer{fd};
  struct stat st {};
  if (::fstat(fd, &st) != 0) {
    throwIoError("cannot stat", what, errno);
  }
  const auto fileBytes = static_cast<std::size_t>(std::max<off_t>(st.st_size, 0));
  std::vector<std::byte> head(std::min<std::size_t>(fileBytes, kMaxHeaderBytes));
  head.resize(detail::readAt(fd, 0, head, what));
  const detail::AaraHeader header = detail::decodeAaraHeader(head, what);
  checkLength(header, fileBytes, what);
  AaraArray array;
  array.type = header.type;
  array.sizes = header.sizes;
  array.data.resize(header.dataBytes);
  // A file that shrank since fstat reads short: truncated as well.
  checkLength(header, header.headerBytes + detail::readAt(fd, header.headerBytes, array.data, what),
              what);
  return array;
}

}  // namespace vsm::core
