#include "server/api/static_routes.hpp"

#include "server/api/etags.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>

#include "core/common/error.hpp"

namespace vsm::server::api {

namespace fs = std::filesystem;
using core::Error;
using core::ErrorCode;

namespace {

constexpr std::size_t kMaxStaticFileBytes = std::size_t{256} << 20;
constexpr std::size_t kMaxRelativePath = 1024;

/// True when `inner` is `outer` or lies below it (both canonical, compared by components, so
/// "/a/bc" is not under "/a/b").
bool isUnder(const fs::path& inner, const fs::path& outer) {
  auto o = outer.begin();
  auto i = inner.begin();
  for (; o != outer.end(); ++o, ++i) {
    if (i == inner.end() || *i != *o) {
      return false;
    }
  }
  return true;
}

/// Closes a descriptor on every path out of the handler.
struct Fd {
  int fd = -1;
  explicit Fd(int f) : fd(f) {}
  Fd(const Fd&) = delete;
  Fd& operator=(const Fd&) = delete;
  ~Fd() {
    if (fd >= 0) {
      ::close(fd);
    }
  }
};

[[noreturn]] void noSuchFile(std::string_view prefix, std::string_view relative) {
  throw Error(ErrorCode::NotFound,
              "no file " + std::string(prefix) + "/" + std::string(relative.substr(0, 200)));
}

http::Response serve(const std::string& prefix, const fs::path& root,
                     const http::Request& request) {
  const std::string& relative = request.param("path");
  if (relative.empty() && !request.path().ends_with('/')) {
    http::Response redirect;
    redirect.status = 301;
    std::string location = prefix + "/";
    if (!request.query().empty()) {
      location += "?" + std::string(request.query());
    }
    redirect.set("Location", std::move(location));
    return redirect;
  }
  const std::optional<fs::path> file = resolveStaticFile(root, relative);
  if (!file) {
    noSuchFile(prefix, relative);
  }
  // O_NOFOLLOW: the path is resolved already; a link swapped in since is not followed.
  const Fd fd(::open(file->c_str(), O_RDONLY | O_CLOEXEC | O_NOFOLLOW));
  struct stat st {};
  if (fd.fd < 0 || ::fstat(fd.fd, &st) != 0 || !S_ISREG(st.st_mode) ||
      static_cast<std::size_t>(st.st_size) > kMaxStaticFileBytes) {
    noSuchFile(prefix, relative);
  }
  const std::string etag =
      staticFileEtag(static_cast<std::uint64_t>(st.st_size),
                     static_cast<std::uint64_t>(st.st_mtim.tv_sec) * 1'000'000'000ULL +
                         static_cast<std::uint64_t>(st.st_mtim.tv_nsec),
                     static_cast<std::uint64_t>(st.st_ino));
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, http::cache_control::kRevalidate);
  }
  http::Response response;
  response.body.resize(static_cast<std::size_t>(st.st_size));
  std::size_t done = 0;
  while (done < response.body.size()) {
    const ssize_t n = ::read(fd.fd, response.body.data() + done, response.body.size() - done);
    if (n < 0 && errno == EINTR) {
      continue;
    }
    if (n < 0) {
      core::throwIoError("cannot read", file->string(), errno);
    }
    if (n == 0) {
      break;  // truncated meanwhile: serve what is there
    }
    done += static_cast<std::size_t>(n);
  }
  response.body.resize(done);
  response.contentType = std::string(staticContentType(*file));
  response.set("ETag", etag);
  response.set("Cache-Control", std::string(http::cache_control::kRevalidate));
  response.set("X-Content-Type-Options", "nosniff");
  return response;
}

}  // namespace

std::optional<fs::path> resolveStaticFile(const fs::path& root, std::string_view relative) {
  if (relative.size() > kMaxRelativePath) {
    return std::nullopt;
  }
  fs::path candidate = root;
  bool directory = true;
  while (!relative.empty()) {
    const std::size_t slash = relative.find('/');
    const std::string_view component = relative.substr(0, slash);
    const bool last = slash == std::string_view::npos;
    if (component.empty() || component.front() == '.' ||
        component.find_first_of(std::string_view("\\\0", 2)) != std::string_view::npos) {
      return std::nullopt;
    }
    candidate /= fs::path(std::string(component));
    directory = !last;
    relative = last ? std::string_view() : relative.substr(slash + 1);
  }
  if (directory) {
    candidate /= "index.html";
  }
  std::error_code ec;
  const fs::path resolved = fs::canonical(candidate, ec);
  if (ec || !isUnder(resolved, root) || !fs::is_regular_file(resolved, ec) || ec) {
    return std::nullopt;
  }
  return resolved;
}

std::string_view staticContentType(const fs::path& file) {
  std::string ext = file.extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) {
    return static_cast<char>(c >= 'A' && c <= 'Z' ? c - 'A' + 'a' : c);
  });
  struct Type {
    std::string_view ext;
    std::string_view type;
  };
  static constexpr Type kTypes[] = {
      {".html", "text/html; charset=utf-8"},
      {".htm", "text/html; charset=utf-8"},
      {".js", "text/javascript; charset=utf-8"},
      {".mjs", "text/javascript; charset=utf-8"},
      {".css", "text/css; charset=utf-8"},
      {".json", "application/json"},
      {".map", "application/json"},
      {".wasm", "application/wasm"},
      {".txt", "text/plain; charset=utf-8"},
      {".xml", "application/xml"},
      {".svg", "image/svg+xml"},
      {".png", "image/png"},
      {".jpg", "image/jpeg"},
      {".jpeg", "image/jpeg"},
      {".gif", "image/gif"},
      {".webp", "image/webp"},
      {".ktx2", "image/ktx2"},
      {".glb", "model/gltf-binary"},
      {".gltf", "model/gltf+json"},
      {".woff", "font/woff"},
      {".woff2", "font/woff2"},
  };
  for (const Type& t : kTypes) {
    if (ext == t.ext) {
      return t.type;
    }
  }
  return "application/octet-stream";
}

void addStaticRoutes(http::Router& router, std::string prefix, const fs::path& root) {
  if (!prefix.starts_with('/') || prefix.ends_with('/')) {
    throw Error(ErrorCode::InvalidArgument,
                "static route prefix '" + prefix + "' must start and must not end with '/'");
  }
  std::error_code ec;
  fs::path canonical = fs::canonical(root, ec);
  if (ec || !fs::is_directory(canonical, ec)) {
    throw Error(ErrorCode::NotFound,
                "static files directory '" + root.string() + "' is not a directory");
  }
  router.add(http::Method::Get, prefix + "/{path...}",
             [prefix, canonical = std::move(canonical)](const http::Request& request) {
               return serve(prefix, canonical, request);
             });
}

}  // namespace vsm::server::api
