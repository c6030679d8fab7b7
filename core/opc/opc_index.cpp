// vsm's binary index of a hierarchy file (core/opc/README.md, "The index", has the format).
#include "core/opc/opc_index.hpp"

#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <cstdint>
#include <cstring>
#include <functional>
#include <set>

#include "core/common/checksum.hpp"
#include "core/common/error.hpp"
#include "core/opc/opc_detail.hpp"

namespace vsm::core {
namespace fs = std::filesystem;

namespace {

constexpr char kMagic[8] = {'V', 'S', 'M', 'I', 'D', 'X', '\n', '\0'};
// 2 adds the retired folders and the head's checksum after the revision record; 1 is still read.
// 3 is a delta: format 2's head, then what changed since a base (a full index of format 2).
constexpr std::uint32_t kFirstFormat = 1;
constexpr std::uint32_t kFormat = 2;
constexpr std::uint32_t kDeltaFormat = 3;
constexpr std::string_view kBasePrefix = "vsm-index-base-";
constexpr std::string_view kIndexSuffix = ".vsmidx";
constexpr std::string_view kDefaultPositions = "Positions.aara";

class Encoder {
 public:
  template <typename T>
  void put(const T& value) {
    static_assert(std::is_trivially_copyable_v<T>);
    const auto* p = reinterpret_cast<const std::byte*>(&value);
    bytes_.insert(bytes_.end(), p, p + sizeof(T));
  }
  void putString(std::string_view s) {
    put(static_cast<std::uint32_t>(s.size()));
    const auto* p = reinterpret_cast<const std::byte*>(s.data());
    bytes_.insert(bytes_.end(), p, p + s.size());
  }
  /// A key: depth (u8), x, y (u32).
  void putKey(const PatchKey& key) {
    put(static_cast<std::uint8_t>(key.depth));
    put(key.x);
    put(key.y);
  }
  void putBox(const Box3d& b) {
    for (const double v : {b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z}) {
      put(v);
    }
  }
  std::vector<std::byte>& bytes() { return bytes_; }

 private:
  std::vector<std::byte> bytes_;
};

/// Reads what Encoder wrote; `ok()` turns false at the first read past the end.
class Decoder {
 public:
  explicit Decoder(std::span<const std::byte> bytes) : bytes_(bytes) {}
  template <typename T>
  T get() {
    T value{};
    if (pos_ + sizeof(T) > bytes_.size()) {
      ok_ = false;
      return value;
    }
    std::memcpy(&value, bytes_.data() + pos_, sizeof(T));
    pos_ += sizeof(T);
    return value;
  }
  std::string getString() {
    const auto n = get<std::uint32_t>();
    if (!ok_ || n > bytes_.size() - pos_) {
      ok_ = false;
      return {};
    }
    std::string s(reinterpret_cast<const char*>(bytes_.data() + pos_), n);
    pos_ += n;
    return s;
  }
  /// A key as Encoder::putKey wrote it.
  PatchKey getKey() {
    PatchKey key;
    key.depth = get<std::uint8_t>();
    key.x = get<std::uint32_t>();
    key.y = get<std::uint32_t>();
    return key;
  }
  Box3d getBox() {
    Box3d b;
    b.min = {get<double>(), get<double>(), get<double>()};
    b.max = {get<double>(), get<double>(), get<double>()};
    return b;
  }
  bool ok() const { return ok_; }
  /// Marks what was read as malformed.
  void fail() { ok_ = false; }
  std::size_t remaining() const { return bytes_.size() - pos_; }
  bool atEnd() const { return pos_ == bytes_.size(); }

 private:
  std::span<const std::byte> bytes_;
  std::size_t pos_ = 0;
  bool ok_ = true;
};

/// An index file mapped read-only (an index is 200 bytes a patch: mapping it spares copying tens
/// of MB and faulting in a buffer for them). Index files are replaced by renames, never rewritten
/// in place, so the mapping does not change under its reader.
class MappedIndex {
 public:
  /// Throws Error(NotFound) when there is no such file, Error(Io) when it cannot be mapped.
  explicit MappedIndex(const fs::path& file) {
    const int fd = detail::openForReading(file);
    struct stat st {};
    if (::fstat(fd, &st) != 0) {
      const int errnum = errno;
      ::close(fd);
      throw Error(ErrorCode::Io, "cannot stat " + file.string() + ": " + std::strerror(errnum));
    }
    size_ = static_cast<std::size_t>(st.st_size);
    if (size_ > 0) {
      void* map = ::mmap(nullptr, size_, PROT_READ, MAP_PRIVATE | MAP_POPULATE, fd, 0);
      if (map == MAP_FAILED) {
        const int errnum = errno;
        ::close(fd);
        throw Error(ErrorCode::Io, "cannot map " + file.string() + ": " + std::strerror(errnum));
      }
      data_ = static_cast<const std::byte*>(map);
    }
    ::close(fd);
  }
  ~MappedIndex() {
    if (data_ != nullptr) {
      ::munmap(const_cast<std::byte*>(data_), size_);
    }
  }
  MappedIndex(const MappedIndex&) = delete;
  MappedIndex& operator=(const MappedIndex&) = delete;
  std::span<const std::byte> bytes() const { return {data_, size_}; }

 private:
  const std::byte* data_ = nullptr;
  std::size_t size_ = 0;
};

void putStamp(Encoder& out, const HierarchyStamp& stamp) {
  // The device number is left out: it may differ after a remount while the file is the same.
  out.put(stamp.inode);
  out.put(stamp.size);
  out.put(stamp.modifiedNs);
}

}  // namespace

// Fast enough to cost little next to reading the file, and catches a truncated or damaged file.
std::uint64_t opcIndexChecksum(std::span<const std::byte> bytes) {
  return checksum64(bytes);
}

std::string indexFileName(std::string_view hierarchyName) {
  std::string_view stem = hierarchyName;
  if (const auto dot = stem.rfind('.'); dot != std::string_view::npos) {
    stem = stem.substr(0, dot);
  }
  return std::string(stem) + std::string(kIndexSuffix);
}

bool isIndexFileName(std::string_view name) {
  return name.size() > kIndexSuffix.size() && name.ends_with(kIndexSuffix);
}

HierarchyStamp fileStamp(const fs::path& file) {
  struct stat st {};
  if (::stat(file.c_str(), &st) != 0) {
    throw Error(ErrorCode::Io, "cannot stat " + file.string() + ": " + std::strerror(errno));
  }
  return HierarchyStamp{static_cast<std::uint64_t>(st.st_dev),
                        static_cast<std::uint64_t>(st.st_ino),
                        static_cast<std::uint64_t>(st.st_size),
                        std::int64_t{st.st_mtim.tv_sec} * 1'000'000'000 + st.st_mtim.tv_nsec};
}

namespace {

/// The head of an index of `format` (2 or 3), up to and with the head's checksum.
void putHead(Encoder& out, std::uint32_t format, const HierarchyStamp& stamp, const Model& model,
             const RevisionRecord* record, const std::vector<RetiredFolder>* retired) {
  for (const char c : kMagic) {
    out.put(c);
  }
  out.put(format);
  putStamp(out, stamp);
  out.put(static_cast<std::int32_t>(model.gridSize()));
  // The summary `vsm info` prints, with its own checksum: read without the patches.
  const std::vector<LevelSummary> levels = model.levels();
  out.put(static_cast<std::uint64_t>(model.patchCount()));
  out.putBox(model.empty() ? Box3d{} : model.at(PatchKey::root()).globalBox);
  out.put(static_cast<std::uint32_t>(levels.size()));
  for (const LevelSummary& level : levels) {
    out.put(static_cast<std::int32_t>(level.depth));
    out.put(static_cast<std::uint64_t>(level.patches));
    out.put(static_cast<std::uint64_t>(level.leaves));
    out.putBox(level.bounds);
    out.put(level.resolution);
  }
  out.put(opcIndexChecksum(out.bytes()));
  out.put(static_cast<std::uint8_t>(record != nullptr));
  if (record != nullptr) {
    out.put(record->parent);
    out.putString(record->time);
    out.putString(record->job);
    out.put(record->changed);
    out.put(record->removed);
    out.put(record->restoredFrom);
    out.putString(record->nonce);
    out.put(static_cast<std::uint8_t>(record->fence.has_value()));
    if (record->fence) {
      out.put(record->fence->takeover);
      out.put(record->fence->lease);
    }
  }
  // The folders retired from the parent, then the head's checksum: dropping the parent revision
  // reads this far and no further (LiveModel::dropRevisions).
  out.put(static_cast<std::uint8_t>(retired != nullptr));
  if (retired != nullptr) {
    out.put(static_cast<std::uint64_t>(retired->size()));
    for (const RetiredFolder& entry : *retired) {
      out.putKey(entry.key);
      out.putString(entry.folder);
    }
  }
  out.put(opcIndexChecksum(out.bytes()));
}

void putPatch(Encoder& out, const PatchKey& key, const PatchInfo& info) {
  out.putKey(key);
  out.putString(info.ownFolder() ? info.folder() : std::string());
  out.putBox(info.globalBox);
  out.putBox(info.localBox);
  // Bit 0: Local2Global is a translation; bit 1: the patch is a hidden level's.
  const bool translation = info.local2global().isTranslation();
  out.put(static_cast<std::uint8_t>((translation ? 1 : 0) | (info.hidden ? 2 : 0)));
  if (translation) {
    const Vec3d t = info.local2global().translationPart();
    out.put(t.x);
    out.put(t.y);
    out.put(t.z);
  } else {
    for (const double v : info.local2global().m) {
      out.put(v);
    }
  }
  out.put(info.resolution);
  out.put(info.version);
  out.put(static_cast<std::int32_t>(info.stored.x0));
  out.put(static_cast<std::int32_t>(info.stored.y0));
  out.put(static_cast<std::int32_t>(info.stored.x1));
  out.put(static_cast<std::int32_t>(info.stored.y1));
  // The usual name as an empty string: most patches store Positions.aara.
  out.putString(info.positionsFile() == kDefaultPositions ? std::string_view()
                                                          : std::string_view(info.positionsFile()));
  out.putString(info.coordinatesFile());
  out.putString(info.textureFile());
}

}  // namespace

std::vector<std::byte> encodeOpcIndex(const HierarchyStamp& stamp, const Model& model,
                                      const RevisionRecord* record,
                                      const std::vector<RetiredFolder>* retired) {
  Encoder out;
  putHead(out, kFormat, stamp, model, record, retired);
  out.put(static_cast<std::uint64_t>(model.patchCount()));
  out.bytes().reserve(out.bytes().size() + model.patchCount() * 200 + 8);
  for (const auto& [key, info] : model.patches()) {
    putPatch(out, key, info);
  }
  out.put(opcIndexChecksum(out.bytes()));
  return std::move(out.bytes());
}

std::vector<std::byte> encodeOpcIndexDelta(const HierarchyStamp& stamp, const Model& model,
                                           const RevisionRecord* record,
                                           const std::vector<RetiredFolder>* retired,
                                           const IndexBase& base, const std::set<PatchKey>& changed,
                                           const std::set<PatchKey>& removed) {
  Encoder out;
  putHead(out, kDeltaFormat, stamp, model, record, retired);
  out.putString(base.name);
  out.put(base.size);
  out.put(base.checksum);
  out.put(static_cast<std::uint64_t>(changed.size()));
  for (const PatchKey& key : changed) {
    putPatch(out, key, model.at(key));
  }
  out.put(static_cast<std::uint64_t>(removed.size()));
  for (const PatchKey& key : removed) {
    out.putKey(key);
  }
  out.put(opcIndexChecksum(out.bytes()));
  return std::move(out.bytes());
}

namespace {

/// The index's head up to its patches: the grid size, the revision record, the retired folders
/// (format 2) and the number of patches.
struct IndexHead {
  int gridSize = 0;
  std::optional<RevisionRecord> record;
  std::optional<std::vector<RetiredFolder>> retired;
  std::uint64_t count = 0;
};

/// The format (1, 2 or 3) when `in` starts with the format and `stamp` (any stamp when null)
/// after the magic; else 0.
std::uint32_t readFormatAndStamp(Decoder& in, const HierarchyStamp* stamp) {
  const auto format = in.get<std::uint32_t>();
  const auto inode = in.get<std::uint64_t>();
  const auto size = in.get<std::uint64_t>();
  const auto modified = in.get<std::int64_t>();
  if (!in.ok() || format < kFirstFormat || format > kDeltaFormat ||
      (stamp != nullptr &&
       (inode != stamp->inode || size != stamp->size || modified != stamp->modifiedNs))) {
    return 0;
  }
  return format;
}

/// The head after the format and stamp, up to (not including) the head's checksum of format 2 or
/// the patch count of format 1; !in.ok() when it is cut short.
IndexHead readHeadFields(Decoder& in, std::uint32_t format) {
  IndexHead head;
  head.gridSize = in.get<std::int32_t>();
  in.get<std::uint64_t>();
  in.getBox();
  const auto levels = in.get<std::uint32_t>();
  if (!in.ok() || levels > 64) {
    in.fail();
    return head;
  }
  for (std::uint32_t i = 0; i < levels; ++i) {
    in.get<std::int32_t>();
    in.get<std::uint64_t>();
    in.get<std::uint64_t>();
    in.getBox();
    in.get<double>();
  }
  in.get<std::uint64_t>();  // the summary's checksum (readOpcIndexSummary checks it)
  if (in.get<std::uint8_t>() != 0) {
    RevisionRecord record;
    record.parent = in.get<std::uint64_t>();
    record.time = in.getString();
    record.job = in.getString();
    record.changed = in.get<std::uint64_t>();
    record.removed = in.get<std::uint64_t>();
    record.restoredFrom = in.get<std::uint64_t>();
    record.nonce = in.getString();
    if (in.get<std::uint8_t>() != 0) {
      FencingToken token;
      token.takeover = in.get<std::uint64_t>();
      token.lease = in.get<std::int64_t>();
      record.fence = token;
    }
    head.record = std::move(record);
  }
  if (format >= 2 && in.get<std::uint8_t>() != 0) {
    const auto count = in.get<std::uint64_t>();
    // Each entry takes at least 13 bytes: a count beyond what is left is cut short (or damage).
    if (!in.ok() || count > in.remaining() / 13) {
      in.fail();
      return head;
    }
    std::vector<RetiredFolder> retired(count);
    for (RetiredFolder& entry : retired) {
      entry.key = in.getKey();
      entry.folder = in.getString();
    }
    head.retired = std::move(retired);
  }
  return head;
}

/// The head of a whole index `bytes` (whose checksum it checks) read by `in` from after the magic,
/// up to its patches; nullopt when it is not an index of `stamp`.
std::optional<IndexHead> decodeHead(std::span<const std::byte> bytes, const HierarchyStamp* stamp,
                                    Decoder& in) {
  const std::uint32_t format = readFormatAndStamp(in, stamp);
  if (format == 0 || format == kDeltaFormat) {
    return std::nullopt;
  }
  std::uint64_t sum;
  std::memcpy(&sum, bytes.data() + bytes.size() - 8, 8);
  if (opcIndexChecksum(bytes.first(bytes.size() - 8)) != sum) {
    return std::nullopt;
  }
  IndexHead head = readHeadFields(in, format);
  if (format >= 2) {
    in.get<std::uint64_t>();  // the head's checksum (the file's covers it)
  }
  head.count = in.get<std::uint64_t>();
  if (!in.ok() || head.count == 0 || head.count > bytes.size()) {
    return std::nullopt;
  }
  return head;
}

/// One patch of the index into `info`; false past the end or for a key out of range.
bool decodePatch(Decoder& in, PatchInfo& info) {
  info.key = in.getKey();
  info.setFolder(in.getString());
  info.globalBox = in.getBox();
  info.localBox = in.getBox();
  const auto flags = in.get<std::uint8_t>();
  if (flags > 3) {
    return false;
  }
  info.hidden = (flags & 2) != 0;
  if ((flags & 1) != 0) {
    const Vec3d t{in.get<double>(), in.get<double>(), in.get<double>()};
    info.setLocal2Global(Mat4d::translation(t));
  } else {
    Mat4d m;
    for (double& v : m.m) {
      v = in.get<double>();
    }
    info.setLocal2Global(m);
  }
  info.resolution = in.get<double>();
  info.version = in.get<std::uint64_t>();
  GridRect stored;
  stored.x0 = in.get<std::int32_t>();
  stored.y0 = in.get<std::int32_t>();
  stored.x1 = in.get<std::int32_t>();
  stored.y1 = in.get<std::int32_t>();
  if (!PackedRect::fits(stored)) {
    return false;
  }
  info.stored = stored;
  PatchFiles files;
  files.positions = in.getString();
  if (files.positions.empty()) {
    files.positions = kDefaultPositions;
  }
  files.coordinates = in.getString();
  files.texture = in.getString();
  info.setFiles(std::move(files));
  return in.ok() && info.key.depth <= PatchKey::kMaxDepth;
}

bool hasMagic(std::span<const std::byte> bytes) {
  return bytes.size() >= sizeof(kMagic) + 8 &&
         std::memcmp(bytes.data(), kMagic, sizeof(kMagic)) == 0;
}

/// The format of index bytes (after the magic); 0 when they are not an index.
std::uint32_t formatOf(std::span<const std::byte> bytes) {
  if (!hasMagic(bytes)) {
    return 0;
  }
  std::uint32_t format;
  std::memcpy(&format, bytes.data() + sizeof(kMagic), 4);
  return format;
}

/// A delta (format 3): its head, and after it the base it builds on and what changed since.
struct Delta {
  IndexHead head;
  IndexBase base;
  std::vector<PatchInfo> changed;  // in key order
  std::set<PatchKey> removed;
};

/// The delta `bytes` if they are one of a hierarchy of `stamp` (any stamp when null) whose
/// checksum holds; nullopt otherwise.
std::optional<Delta> decodeDelta(std::span<const std::byte> bytes, const HierarchyStamp* stamp) {
  if (!hasMagic(bytes)) {
    return std::nullopt;
  }
  Decoder in(bytes.subspan(sizeof(kMagic), bytes.size() - sizeof(kMagic) - 8));
  if (readFormatAndStamp(in, stamp) != kDeltaFormat) {
    return std::nullopt;
  }
  std::uint64_t sum;
  std::memcpy(&sum, bytes.data() + bytes.size() - 8, 8);
  if (opcIndexChecksum(bytes.first(bytes.size() - 8)) != sum) {
    return std::nullopt;
  }
  Delta delta;
  delta.head = readHeadFields(in, kDeltaFormat);
  in.get<std::uint64_t>();  // the head's checksum (the file's covers it)
  delta.base.name = in.getString();
  delta.base.size = in.get<std::uint64_t>();
  delta.base.checksum = in.get<std::uint64_t>();
  const auto changed = in.get<std::uint64_t>();
  // A patch takes at least 150 bytes, a key 9: counts beyond what is left are damage.
  if (!in.ok() || !isIndexBaseFileName(delta.base.name) || changed > in.remaining() / 150) {
    return std::nullopt;
  }
  delta.changed.resize(changed);
  for (std::size_t i = 0; i < delta.changed.size(); ++i) {
    if (!decodePatch(in, delta.changed[i]) ||
        (i > 0 && !(delta.changed[i - 1].key < delta.changed[i].key))) {
      return std::nullopt;
    }
  }
  const auto removed = in.get<std::uint64_t>();
  if (!in.ok() || removed > in.remaining() / 9) {
    return std::nullopt;
  }
  for (std::uint64_t i = 0; i < removed; ++i) {
    delta.removed.insert(in.getKey());
  }
  if (!in.ok() || !in.atEnd()) {
    return std::nullopt;
  }
  return delta;
}

/// The checksum a file of index bytes ends with.
std::uint64_t trailingChecksum(std::span<const std::byte> bytes) {
  std::uint64_t sum = 0;
  std::memcpy(&sum, bytes.data() + bytes.size() - 8, 8);
  return sum;
}

/// The `count` patches of a full index after its head, in key order, as a model of `gridSize`;
/// nullopt when they are malformed or the bytes go on after them.
std::optional<Model> decodeModel(Decoder& in, int gridSize, std::uint64_t count) {
  try {
    Model model(gridSize);
    for (std::uint64_t i = 0; i < count; ++i) {
      PatchInfo info;
      if (!decodePatch(in, info)) {
        return std::nullopt;
      }
      model.insert(std::move(info));  // parents first: the index is in key order
    }
    if (!in.atEnd()) {
      return std::nullopt;
    }
    return model;
  } catch (const Error&) {
    return std::nullopt;  // a key twice, a child without its parent: not an index we wrote
  }
}

/// The model of `base`, the bytes of the base `delta` names, when they are that base (its size and
/// checksum), whole, of the delta's patch size; nullopt otherwise.
std::optional<Model> decodeBase(const Delta& delta, std::span<const std::byte> base) {
  if (base.size() != delta.base.size || !hasMagic(base) ||
      trailingChecksum(base) != delta.base.checksum) {
    return std::nullopt;
  }
  // A full index of another hierarchy (its stamp is not this one's).
  Decoder in(base.subspan(sizeof(kMagic), base.size() - sizeof(kMagic) - 8));
  const std::optional<IndexHead> head = decodeHead(base, nullptr, in);
  if (!head || head->gridSize != delta.head.gridSize) {
    return std::nullopt;
  }
  return decodeModel(in, head->gridSize, head->count);
}

/// `model` (the delta's base) with the delta's patches: the changed ones replacing or joining the
/// base's, the removed ones gone. Its chunks and nodes stay shared with the base's copies wherever
/// the delta does not reach. Nullopt when the delta does not fit the base (a child without its
/// parent, a removed patch with children).
/// The keys whose patches `delta` can change in the model it is applied to: its changed and
/// removed keys and their parents (an insert or a removal changes the parent's child bits).
std::set<PatchKey> keysTouchedBy(const Delta& delta) {
  std::set<PatchKey> keys;
  const auto add = [&keys](const PatchKey& key) {
    keys.insert(key);
    if (const std::optional<PatchKey> parent = key.parent()) {
      keys.insert(*parent);
    }
  };
  for (const PatchInfo& info : delta.changed) {
    add(info.key);
  }
  for (const PatchKey& key : delta.removed) {
    add(key);
  }
  return keys;
}

/// modelDigest(after), from modelDigest(before) (`beforeDigest`) and the keys at which the two
/// can differ: each patch's digest out, the new one in (the digest is a sum).
std::uint64_t digestByChange(const Model& before, std::uint64_t beforeDigest, const Model& after,
                             const std::set<PatchKey>& touched) {
  std::uint64_t digest = beforeDigest;
  for (const PatchKey& key : touched) {
    if (const PatchInfo* old = before.find(key)) {
      digest -= patchDigest(*old);
    }
    if (const PatchInfo* now = after.find(key)) {
      digest += patchDigest(*now);
    }
  }
  return digest;
}

std::optional<Model> applyDelta(Model model, Delta& delta) {
  try {
    // In key order, so parents first: a replaced patch keeps the base's child bits, which the
    // inserts and removals below then change.
    for (PatchInfo& info : delta.changed) {
      if (model.find(info.key) == nullptr) {
        model.insert(std::move(info));
        continue;
      }
      PatchInfo& node = model.edit(info.key);
      const std::uint8_t children = node.childMask;
      node = std::move(info);
      node.childMask = children;
    }
    // Deepest first: a removed patch's removed children are gone before it.
    for (auto key = delta.removed.rbegin(); key != delta.removed.rend(); ++key) {
      if (model.find(*key) != nullptr) {
        model.eraseLeaf(*key);
      }
    }
    return model;
  } catch (const Error&) {
    return std::nullopt;
  }
}

}  // namespace

std::optional<OpcRevision> decodeOpcIndex(std::span<const std::byte> bytes,
                                          const HierarchyStamp& stamp) {
  if (!hasMagic(bytes)) {
    return std::nullopt;
  }
  Decoder in(bytes.subspan(sizeof(kMagic), bytes.size() - sizeof(kMagic) - 8));
  std::optional<IndexHead> head = decodeHead(bytes, &stamp, in);
  if (!head) {
    return std::nullopt;
  }
  std::optional<Model> model = decodeModel(in, head->gridSize, head->count);
  if (!model) {
    return std::nullopt;
  }
  return OpcRevision{std::move(*model), std::move(head->record)};
}

std::optional<OpcRevision> decodeOpcIndexDelta(std::span<const std::byte> delta,
                                               const HierarchyStamp& stamp,
                                               std::span<const std::byte> base) {
  std::optional<Delta> read = decodeDelta(delta, &stamp);
  if (!read) {
    return std::nullopt;
  }
  std::optional<Model> model = decodeBase(*read, base);
  if (model) {
    model = applyDelta(std::move(*model), *read);
  }
  if (!model) {
    return std::nullopt;
  }
  return OpcRevision{std::move(*model), std::move(read->head.record)};
}

std::shared_ptr<const Model> IndexBaseMemo::find(const IndexBase& base,
                                                 std::uint64_t* digest) const {
  std::lock_guard lock(mutex_);
  // By its bytes (size and checksum), not its name: an adopted base is the full index a reader
  // may have opened from, under another name.
  const bool same = model_ != nullptr && base.size == base_.size && base.checksum == base_.checksum;
  if (same && digest != nullptr) {
    *digest = digest_;
  }
  return same ? model_ : nullptr;
}

std::shared_ptr<const Model> IndexBaseMemo::model() const {
  std::lock_guard lock(mutex_);
  return model_;
}

std::uint64_t IndexBaseMemo::keep(const IndexBase& base, std::shared_ptr<const Model> model) {
  const std::uint64_t digest = modelDigest(*model);
  std::lock_guard lock(mutex_);
  base_ = base;
  model_ = std::move(model);
  digest_ = digest;
  return digest;
}

bool isIndexBaseFileName(std::string_view name) {
  return name.starts_with(kBasePrefix) && isIndexFileName(name) && detail::isSafeName(name);
}

namespace {

/// The index `index` of the hierarchy file `hierarchyFile` (a full one, or a delta with its base
/// beside it, or in `memo`), when current; nullopt otherwise.
std::optional<OpcRevision> readIndexOf(const fs::path& hierarchyFile, const fs::path& index,
                                       IndexBaseMemo* memo) {
  struct stat st {};
  if (::stat(index.c_str(), &st) != 0) {
    return std::nullopt;
  }
  try {
    const HierarchyStamp stamp = fileStamp(hierarchyFile);
    const MappedIndex mapped(index);
    if (formatOf(mapped.bytes()) != kDeltaFormat) {
      std::optional<OpcRevision> full = decodeOpcIndex(mapped.bytes(), stamp);
      if (full && memo != nullptr) {
        // Kept as a base: the next publish adopts this index as its base (stagePublishedIndex),
        // so the reader's next read applies the delta alone. The copy shares the chunks.
        full->digest =
            memo->keep(IndexBase{{}, mapped.bytes().size(), trailingChecksum(mapped.bytes())},
                       std::make_shared<const Model>(full->model));
      }
      return full;
    }
    std::optional<Delta> delta = decodeDelta(mapped.bytes(), &stamp);
    if (!delta) {
      return std::nullopt;
    }
    std::optional<Model> model;
    std::optional<std::uint64_t> digest;
    std::uint64_t baseDigest = 0;
    std::shared_ptr<const Model> known =
        memo != nullptr ? memo->find(delta->base, &baseDigest) : nullptr;
    std::optional<Model> base;
    if (known == nullptr) {
      base = decodeBase(*delta, MappedIndex(index.parent_path() / delta->base.name).bytes());
      if (base && memo != nullptr) {
        known = std::make_shared<const Model>(std::move(*base));
        base.reset();
        baseDigest = memo->keep(delta->base, known);
      }
    }
    if (known != nullptr) {
      const std::set<PatchKey> touched = keysTouchedBy(*delta);
      model = applyDelta(*known, *delta);  // a copy of its chunk pointers: ~1/256 of its patches
      if (model) {
        digest = digestByChange(*known, baseDigest, *model, touched);
      }
    } else if (base) {
      model = applyDelta(std::move(*base), *delta);
    }
    if (!model) {
      return std::nullopt;
    }
    return OpcRevision{std::move(*model), std::move(delta->head.record), digest};
  } catch (const Error&) {
    return std::nullopt;  // unreadable: the full read says what is wrong, if anything
  }
}

}  // namespace

bool forEachIndexedFolder(const fs::path& hierarchyFile,
                          const std::function<void(std::string_view)>& fn) {
  try {
    const HierarchyStamp stamp = fileStamp(hierarchyFile);
    const MappedIndex index(hierarchyFile.parent_path() /
                            indexFileName(hierarchyFile.filename().string()));
    const std::span<const std::byte> bytes = index.bytes();
    if (formatOf(bytes) == kDeltaFormat) {
      const std::optional<OpcRevision> read = readIndexOf(
          hierarchyFile,
          hierarchyFile.parent_path() / indexFileName(hierarchyFile.filename().string()), nullptr);
      if (read) {
        for (const auto& [key, info] : read->model.patches()) {
          fn(info.folder());
        }
      }
      return read.has_value();
    }
    if (!hasMagic(bytes)) {
      return false;
    }
    Decoder in(bytes.subspan(sizeof(kMagic), bytes.size() - sizeof(kMagic) - 8));
    const std::optional<IndexHead> head = decodeHead(bytes, &stamp, in);
    if (!head) {
      return false;
    }
    // The checksum held: every record is as encodeOpcIndex wrote it, so a decode error below is
    // a bug, not damage (decodePatch still stops at the end).
    PatchInfo info;
    for (std::uint64_t i = 0; i < head->count; ++i) {
      if (!decodePatch(in, info)) {
        return false;
      }
      fn(info.folder());
    }
    return in.atEnd();
  } catch (const Error&) {
    return false;  // none, or unreadable: the caller reads the hierarchy
  }
}

std::optional<OpcSummary> readOpcIndexSummary(const fs::path& dir) {
  const auto patches = detail::findEntry(dir, "Patches");
  const auto hierarchy = patches ? detail::findEntry(*patches, "patchhierarchy.xml") : std::nullopt;
  if (!hierarchy) {
    return std::nullopt;
  }
  try {
    const HierarchyStamp stamp = fileStamp(*hierarchy);
    // The header and the summary only: 64 levels at most, well within 8 KiB.
    const std::vector<std::byte> bytes =
        detail::readFile(*patches / indexFileName("patchhierarchy.xml"), 8192);
    if (bytes.size() < sizeof(kMagic) || std::memcmp(bytes.data(), kMagic, sizeof(kMagic)) != 0) {
      return std::nullopt;
    }
    Decoder in{std::span<const std::byte>(bytes).subspan(sizeof(kMagic))};
    if (readFormatAndStamp(in, &stamp) == 0) {
      return std::nullopt;
    }
    OpcSummary summary;
    summary.gridSize = in.get<std::int32_t>();
    summary.patches = in.get<std::uint64_t>();
    summary.bounds = in.getBox();
    const auto levels = in.get<std::uint32_t>();
    if (!in.ok() || levels > 64) {
      return std::nullopt;
    }
    for (std::uint32_t i = 0; i < levels; ++i) {
      LevelSummary level;
      level.depth = in.get<std::int32_t>();
      level.patches = in.get<std::uint64_t>();
      level.leaves = in.get<std::uint64_t>();
      level.bounds = in.getBox();
      level.resolution = in.get<double>();
      summary.levels.push_back(level);
    }
    const std::size_t end = bytes.size() - in.remaining();
    const auto sum = in.get<std::uint64_t>();
    if (!in.ok() || opcIndexChecksum(std::span<const std::byte>(bytes).first(end)) != sum) {
      return std::nullopt;
    }
    return summary;
  } catch (const Error&) {
    return std::nullopt;
  }
}

std::optional<IndexedRevision> decodeOpcIndexHead(std::span<const std::byte> bytes,
                                                  const HierarchyStamp& stamp) {
  if (!hasMagic(bytes)) {
    return std::nullopt;
  }
  Decoder in{bytes.subspan(sizeof(kMagic))};
  const std::uint32_t format = readFormatAndStamp(in, &stamp);
  if (format < kFormat) {
    return std::nullopt;  // format 1 has no head checksum: its head is not trusted alone
  }
  IndexHead head = readHeadFields(in, format);
  const std::size_t end = bytes.size() - in.remaining();
  const auto sum = in.get<std::uint64_t>();
  if (!in.ok() || opcIndexChecksum(bytes.first(end)) != sum) {
    return std::nullopt;
  }
  return IndexedRevision{std::move(head.record), std::move(head.retired)};
}

std::optional<IndexedRevision> readIndexedRevision(const fs::path& hierarchyFile) {
  try {
    const HierarchyStamp stamp = fileStamp(hierarchyFile);
    const fs::path file =
        hierarchyFile.parent_path() / indexFileName(hierarchyFile.filename().string());
    // The head grows with the retired folders (a few kB after a small merge): read 64 KiB, and
    // more only when that does not hold it.
    for (std::size_t limit = std::size_t{1} << 16;; limit *= 16) {
      const std::vector<std::byte> bytes = detail::readFile(file, limit);
      std::optional<IndexedRevision> head = decodeOpcIndexHead(bytes, stamp);
      if (head || bytes.size() < limit) {
        return head;
      }
    }
  } catch (const Error&) {
    return std::nullopt;  // none, or unreadable
  }
}

std::optional<OpcRevision> readOpcIndex(const fs::path& dir, std::string_view hierarchyName,
                                        IndexBaseMemo* memo) {
  const auto patches = detail::findEntry(dir, "Patches");
  if (!patches) {
    return std::nullopt;
  }
  const auto hierarchy = detail::findEntry(*patches, hierarchyName);
  if (!hierarchy) {
    return std::nullopt;
  }
  return readIndexOf(*hierarchy, *patches / indexFileName(hierarchyName), memo);
}

std::optional<IndexBase> readIndexBase(const fs::path& index) {
  try {
    for (std::size_t limit = std::size_t{1} << 16;; limit *= 16) {
      const std::vector<std::byte> bytes = detail::readFile(index, limit);
      if (formatOf(bytes) != kDeltaFormat) {
        return std::nullopt;
      }
      Decoder in{std::span<const std::byte>(bytes).subspan(sizeof(kMagic))};
      readFormatAndStamp(in, nullptr);
      readHeadFields(in, kDeltaFormat);
      in.get<std::uint64_t>();
      IndexBase base;
      base.name = in.getString();
      base.size = in.get<std::uint64_t>();
      base.checksum = in.get<std::uint64_t>();
      if (in.ok()) {
        return isIndexBaseFileName(base.name) ? std::optional(base) : std::nullopt;
      }
      if (bytes.size() < limit) {
        return std::nullopt;
      }
    }
  } catch (const Error&) {
    return std::nullopt;
  }
}

namespace {

/// True when `base` in `patches` is the file a delta names: its size and final checksum.
bool baseIsThere(const fs::path& patches, const IndexBase& base) {
  try {
    const fs::path file = patches / base.name;
    struct stat st {};
    if (::stat(file.c_str(), &st) != 0 || static_cast<std::uint64_t>(st.st_size) != base.size ||
        base.size < 16) {
      return false;
    }
    const int fd = detail::openForReading(file);
    std::array<std::byte, 8> tail{};
    std::size_t got = 0;
    try {
      got = detail::readAt(fd, base.size - 8, tail, file.string());
    } catch (...) {
      ::close(fd);
      throw;
    }
    ::close(fd);
    return got == 8 && trailingChecksum(tail) == base.checksum;
  } catch (const Error&) {
    return false;
  }
}

}  // namespace

StagedIndex stagePublishedIndex(const fs::path& dir, const fs::path& hierarchyFile,
                                const Model& model, const RevisionRecord& record,
                                const std::vector<RetiredFolder>& retired,
                                const std::set<PatchKey>& changed,
                                const std::set<PatchKey>& removed,
                                const std::optional<HierarchyStamp>& replaced,
                                const std::string& baseName) {
  const fs::path patches = patchesDirOf(dir);
  const fs::path target = patches / indexFileName("patchhierarchy.xml");
  const HierarchyStamp stamp = fileStamp(hierarchyFile);
  // The current index when it describes the hierarchy this publish replaces: a delta, or a full
  // index whose checksum holds (mapped, not copied: 250 MB at 10^6 patches, checked in ~0.1 s).
  std::optional<Delta> previous;
  std::optional<IndexBase> adopted;
  if (replaced) {
    try {
      const MappedIndex current(target);
      const std::span<const std::byte> bytes = current.bytes();
      if (formatOf(bytes) == kDeltaFormat) {
        previous = decodeDelta(bytes, &*replaced);
      } else if (hasMagic(bytes)) {
        Decoder in(bytes.subspan(sizeof(kMagic), bytes.size() - sizeof(kMagic) - 8));
        const std::optional<IndexHead> head = decodeHead(bytes, &*replaced, in);
        if (head && head->gridSize == model.gridSize()) {
          adopted = IndexBase{baseName, bytes.size(), trailingChecksum(bytes)};
        }
      }
    } catch (const Error&) {
      // none, or unreadable: a new base
    }
  }
  // Adopted whatever the change's size: the delta holds at most the new model's patches, never
  // more than a new base would, and the next publish writes a base if it has grown past the share.
  if (adopted) {
    StagedIndex staged;
    staged.adopted = target;
    staged.adoptedAs = patches / baseName;
    staged.index = std::make_unique<durable::PendingFile>(
        target, encodeOpcIndexDelta(stamp, model, &record, &retired, *adopted, changed, removed));
    return staged;
  }
  if (previous && baseIsThere(patches, previous->base)) {
    // What differs from the base now: what differed before and what this publish changed.
    std::set<PatchKey> changedSince;
    std::set<PatchKey> removedSince;
    for (const PatchInfo& info : previous->changed) {
      (model.find(info.key) != nullptr ? changedSince : removedSince).insert(info.key);
    }
    for (const PatchKey& key : previous->removed) {
      (model.find(key) != nullptr ? changedSince : removedSince).insert(key);
    }
    for (const PatchKey& key : changed) {
      changedSince.insert(key);
    }
    for (const PatchKey& key : removed) {
      removedSince.insert(key);
    }
    if ((changedSince.size() + removedSince.size()) * kIndexDeltaShare <= model.patchCount()) {
      StagedIndex staged;
      staged.index = std::make_unique<durable::PendingFile>(
          target, encodeOpcIndexDelta(stamp, model, &record, &retired, previous->base, changedSince,
                                      removedSince));
      return staged;
    }
  }
  const std::vector<std::byte> full = encodeOpcIndex(stamp, model, &record, &retired);
  const IndexBase base{baseName, full.size(), trailingChecksum(full)};
  StagedIndex staged;
  staged.base = std::make_unique<durable::PendingFile>(patches / baseName, full);
  staged.index = std::make_unique<durable::PendingFile>(
      target, encodeOpcIndexDelta(stamp, model, &record, &retired, base, {}, {}));
  return staged;
}

void StagedIndex::commitBase() const {
  if (base) {
    base->commit();
    durable::syncDirectory(base->target().parent_path());
    return;
  }
  if (adoptedAs.empty()) {
    return;
  }
  // The adopted index is never written again (a publish replaces it by a rename), so a link is
  // its bytes under the base's name; where the file system refuses one, a copy of them.
  durable::DraftWriter links;
  if (!links.link(adopted, adoptedAs)) {
    durable::PendingFile(adoptedAs, MappedIndex(adopted).bytes()).commit();
  }
  durable::syncDirectory(adoptedAs.parent_path());
}

std::unique_ptr<durable::PendingFile> stageOpcIndex(const fs::path& dir,
                                                    std::string_view hierarchyName,
                                                    const fs::path& hierarchyFile,
                                                    const Model& model,
                                                    const RevisionRecord* record) {
  const std::vector<std::byte> bytes = encodeOpcIndex(fileStamp(hierarchyFile), model, record);
  return std::make_unique<durable::PendingFile>(patchesDirOf(dir) / indexFileName(hierarchyName),
                                                bytes);
}

std::size_t writeOpcIndex(const fs::path& dir, std::string_view hierarchyName) {
  const fs::path patches = patchesDirOf(dir);
  const auto hierarchy = detail::findEntry(patches, hierarchyName);
  if (!hierarchy) {
    throw Error(ErrorCode::NotFound,
                "no OPC at '" + dir.string() + "' (no Patches/" + std::string(hierarchyName) + ")");
  }
  const HierarchyStamp before = fileStamp(*hierarchy);
  detail::OpcContents contents = detail::readOpc(dir, hierarchyName);
  if (fileStamp(*hierarchy) != before) {
    throw Error(ErrorCode::Conflict, hierarchy->string() + " changed while it was read");
  }
  const std::vector<std::byte> bytes =
      encodeOpcIndex(before, contents.model, contents.revision ? &*contents.revision : nullptr);
  durable::writeFileAtomically(patches / indexFileName(hierarchyName), bytes);
  return contents.model.patchCount();
}

}  // namespace vsm::core
