#pragma once

#include <filesystem>
#include <optional>
#include <string>
#include <string_view>

#include "server/http/router.hpp"

namespace vsm::server::api {

/// The regular file that the URL path `relative` (below a static route's prefix, percent-decoded,
/// '/'-separated, "" or ending in '/' = that directory's index.html) names under `root`, or
/// nullopt (answered 404) when it names none, or names one outside `root`:
/// - every component must be non-empty (but the last), must not start with '.' (so no "." or
///   "..", and no hidden files) and must not hold '\\' or NUL;
/// - the file, after every symbolic link is resolved, must lie under root's own resolved path
///   (links inside the tree are followed, links out of it are not);
/// - it must be a regular file (a directory without its trailing '/' is not served).
/// `root` must be canonical (std::filesystem::canonical). Touches the file system (stat, readlink);
/// thread-safe.
std::optional<std::filesystem::path> resolveStaticFile(const std::filesystem::path& root,
                                                       std::string_view relative);

/// The Content-Type of a static file by its extension (case-insensitive): text/html,
/// text/javascript
/// (.js, .mjs), text/css, application/json, application/wasm, images, glTF ...;
/// application/octet-stream for anything else.
std::string_view staticContentType(const std::filesystem::path& file);

/// Serves the files under `root` read-only at `prefix` ("/viewer"): GET and HEAD of
/// prefix + "/" + path as resolveStaticFile() finds it, with a strong ETag from the file's size,
/// modification time and inode (If-None-Match -> 304) and "Cache-Control: no-cache" (files change
/// when the viewer is rebuilt); `prefix` alone is redirected (301) to prefix + "/", so relative
/// URLs in index.html resolve. Files larger than 256 MiB are refused (404).
/// Throws core::Error(NotFound) when `root` is not a directory, (InvalidArgument) on a bad prefix.
void addStaticRoutes(http::Router& router, std::string prefix, const std::filesystem::path& root);

}  // namespace vsm::server::api
