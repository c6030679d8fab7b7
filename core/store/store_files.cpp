#include "core/store/store_files.hpp"

#include <dirent.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <memory>
#include <regex>
#include <utility>

#include "core/common/log.hpp"
#include "core/common/random.hpp"
#include "core/durable/durable_io.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/texture_file.hpp"
#include "core/store/live_model.hpp"

namespace fs = std::filesystem;

namespace vsm::core::store {

namespace {

std::string isoTime(std::time_t time) {
  std::tm utc{};
  gmtime_r(&time, &utc);
  char text[32];
  std::strftime(text, sizeof text, "%Y-%m-%dT%H:%M:%SZ", &utc);
  return text;
}

}  // namespace

std::string draftFolder(const PatchKey& key, std::uint64_t version, std::string_view nonce) {
  return key.toString() + "-v" + std::to_string(version) + "-" + std::string(nonce);
}

namespace {

/// The key a folder is named after: the name up to its first '-' read as one; nullopt otherwise.
std::optional<PatchKey> keyOfFolder(std::string_view folder) {
  return PatchKey::parse(folder.substr(0, folder.find('-')));
}

}  // namespace

NamedFolders::NamedFolders(const Model& model) : model_(model) {
  for (const auto& [key, info] : model.patches()) {
    if (info.ownFolder() && keyOfFolder(info.folder()) != key) {
      others_.insert(info.folder());
    }
  }
}

bool NamedFolders::contains(std::string_view folder) const {
  const std::optional<PatchKey> key = keyOfFolder(folder);
  return names(key ? model_.find(*key) : nullptr, folder);
}

bool NamedFolders::names(const PatchInfo* atKey, std::string_view folder) const {
  char buffer[PatchKey::kMaxText];
  return (atKey != nullptr && atKey->folder(buffer) == folder) ||
         others_.contains(std::string(folder));
}

std::vector<PatchKey> NamedFolders::unnamed(const std::vector<PatchKey>& keys) const {
  std::vector<PatchKey> out;
  const Model::Patches patches = model_.patches();
  auto at = patches.begin();
  char text[PatchKey::kMaxText];
  for (const PatchKey& key : keys) {
    while (at != patches.end() && (*at).first < key) {
      ++at;
    }
    const bool found = at != patches.end() && (*at).first == key;
    if (!names(found ? &(*at).second : nullptr, key.toChars(text))) {
      out.push_back(key);
    }
  }
  return out;
}

std::optional<PatchKey> NamedFolders::plainKey(std::string_view folder) {
  std::optional<PatchKey> key = PatchKey::parse(folder);
  char text[PatchKey::kMaxText];
  if (key && key->toChars(text) != folder) {
    key.reset();
  }
  return key;
}

bool isOurFolderName(const std::string& name) {
  // Without a nonce: folders of edits made before nonces, still named by kept revisions.
  static const std::regex pattern("[0-9]+_[0-9]+_[0-9]+(-v[0-9]+(-[0-9a-f]{8})?)?");
  return std::regex_match(name, pattern);
}

bool isOurTileName(const std::string& name) {
  return name.size() > 4 && name.ends_with(".tif") &&
         isOurFolderName(name.substr(0, name.size() - 4));
}

fs::path ourTileFile(const fs::path& dir, const std::string& folder) {
  return dir / "Images" / std::string(kTextureLayer) / (folder + ".tif");
}

std::optional<std::uint64_t> revisionOfFile(std::string_view name) {
  constexpr std::string_view prefix = "vsm-revision-";
  constexpr std::string_view suffix = ".xml";
  if (!name.starts_with(prefix) || !name.ends_with(suffix)) {
    return std::nullopt;
  }
  const std::string_view digits =
      name.substr(prefix.size(), name.size() - prefix.size() - suffix.size());
  std::uint64_t number = 0;
  const auto [end, ec] = std::from_chars(digits.data(), digits.data() + digits.size(), number);
  if (digits.empty() || digits.size() > 19 || ec != std::errc() ||
      end != digits.data() + digits.size()) {
    return std::nullopt;
  }
  return number;
}

std::size_t removeUnnamedHiddenFiles(const fs::path& patches,
                                     const std::set<std::string>& candidates,
                                     const std::vector<fs::path>& hierarchies) {
  std::set<std::string> unnamed = candidates;
  for (const fs::path& hierarchy : hierarchies) {
    if (unnamed.empty()) {
      break;
    }
    if (const std::optional<std::string> named = hiddenHierarchyNamedBy(hierarchy)) {
      unnamed.erase(*named);
    }
  }
  std::size_t removed = 0;
  for (const std::string& name : unnamed) {
    if (::unlink((patches / name).c_str()) == 0) {
      ++removed;
    } else if (errno != ENOENT) {
      log::warn("cannot remove " + (patches / name).string() + ", which no hierarchy names: " +
                std::strerror(errno) + " (retried at the next open)");
    }
  }
  if (removed > 0) {
    durable::syncDirectory(patches);
  }
  return removed;
}

std::map<std::uint64_t, fs::path> revisionFiles(const fs::path& patches) {
  // Read with readdir, not a directory_iterator: Patches/ holds a folder per patch, and only the
  // few names that parse make a path (87k entries: 34 ms instead of ~100 ms, at every publish).
  const std::unique_ptr<DIR, int (*)(DIR*)> dir(::opendir(patches.c_str()), &::closedir);
  if (!dir) {
    throw fs::filesystem_error("cannot list revisions", patches,
                               std::error_code(errno, std::generic_category()));
  }
  std::map<std::uint64_t, fs::path> files;
  errno = 0;
  while (const dirent* entry = ::readdir(dir.get())) {
    if (const auto n = revisionOfFile(entry->d_name)) {
      fs::path file = patches / entry->d_name;
      std::error_code ec;  // a link counts as what it names, as before
      if (entry->d_type == DT_REG || (entry->d_type != DT_DIR && fs::is_regular_file(file, ec))) {
        files.emplace(*n, std::move(file));
      }
    }
    errno = 0;
  }
  if (errno != 0) {
    throw fs::filesystem_error("cannot list revisions", patches,
                               std::error_code(errno, std::generic_category()));
  }
  return files;
}

std::string utcNow() {
  return isoTime(std::time(nullptr));
}

std::optional<std::time_t> parseUtcTime(const std::string& text) {
  std::tm utc{};
  const char* end = ::strptime(text.c_str(), "%Y-%m-%dT%H:%M:%SZ", &utc);
  if (end == nullptr || *end != '\0') {
    return std::nullopt;
  }
  return ::timegm(&utc);
}

std::string fileTime(const fs::path& file) {
  struct stat st {};
  if (::stat(file.c_str(), &st) != 0) {
    return {};
  }
  return isoTime(st.st_mtim.tv_sec);
}

std::shared_ptr<ModelSnapshot> snapshotOf(OpcRevision read, const fs::path& hierarchyFile) {
  auto snapshot = std::make_shared<ModelSnapshot>();
  // The published version is the newest patch version: every publish gives the patches it changes
  // version (published + 1), so every process reading the directory, and every opening after a
  // restart, names the same content by the same version.
  for (const auto& [key, info] : read.model.patches()) {
    snapshot->version = std::max(snapshot->version, info.version);
  }
  snapshot->digest = read.digest ? *read.digest : modelDigest(read.model);
  if (read.record) {
    snapshot->revision = std::move(*read.record);
  } else {
    snapshot->revision.time = fileTime(hierarchyFile);
    for (const auto& [key, info] : read.model.patches()) {
      snapshot->revision.changed += info.version == snapshot->version ? 1 : 0;
    }
  }
  snapshot->model = std::make_shared<const Model>(std::move(read.model));
  return snapshot;
}

void removeFolders(const fs::path& dir, const FolderSet& folders) {
  const fs::path patches = patchesDirOf(dir);
  for (const std::string& folder : folders) {
    std::error_code ec;
    fs::remove_all(patches / folder, ec);
    // Only a tile vsm named for one of its folders is the folder's own (foreign OPCs may share
    // one).
    if (!ec && isOurFolderName(folder)) {
      fs::remove(ourTileFile(dir, folder), ec);
    }
    if (ec) {
      log::warn("cannot remove " + folder + " of a dropped revision: " + ec.message() +
                " (the next open removes it)");
    }
  }
}

std::string normalisedEntry(std::string entry) {
  for (char& c : entry) {
    c = c == '/' ? '\\' : static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  }
  return entry;
}

}  // namespace vsm::core::store
