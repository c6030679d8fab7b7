#pragma once

#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "server/http/message.hpp"

namespace vsm::server::http {

/// Handles one routed request. May throw core::Error; the Pipeline turns it into a JSON error.
/// Runs on the CPU pool, never on a network thread: it may block on disk.
using Handler = std::function<Response(const Request&)>;

/// Answers a routed request on the network thread that read it, when that needs no blocking: from
/// memory that is there already (a cached response body, a 304). Returns nullopt to have the
/// route's Handler run on the CPU pool instead. Must never block: no disk, no encoding, no wait
/// for a lock that is held across I/O (short critical sections are fine). May throw core::Error
/// as a Handler does.
using InlineHandler = std::function<std::optional<Response>(const Request&)>;

/// One route: a method and a path pattern.
struct Route {
  Method method;
  /// As registered, e.g. "/v1/models/{m}/patches/{p}"; also the metrics label of the route.
  std::string pattern;
  Handler handler;
  /// Tried first, on the network thread, when set.
  InlineHandler inlineHandler;
};

/// The outcome of matching a method and a path.
struct RouteMatch {
  enum class Kind { Found, NotFound, MethodNotAllowed };
  Kind kind = Kind::NotFound;
  /// The route, when Found.
  const Route* route = nullptr;
  /// Path parameters, percent-decoded, when Found.
  std::map<std::string, std::string, std::less<>> params;
  /// Methods the path supports (HEAD with GET, OPTIONS always), when Found or MethodNotAllowed.
  std::vector<Method> allowed;
};

/// Maps (method, path) to a handler. A pattern is "/"-separated segments; a segment is a literal
/// ("models") or holds one parameter "{name}" with an optional literal prefix and suffix
/// ("{p}.glb"). A parameter matches one non-empty segment; segments are percent-decoded before
/// comparing, so "%2F" never splits a segment. A last segment "{name...}" is a tail: it matches
/// the rest of the path, zero or more segments (empty ones too), decoded and joined by '/' (so
/// "/viewer/{path...}" matches "/viewer/" with path "" and "/viewer/a/b.js" with "a/b.js"; a
/// handler must check the components itself, "a%2F..%2Fb" arrives as "a/../b"). When several
/// patterns match, the most specific one wins (literal before affixed parameter before bare
/// parameter before tail, decided at the first segment where they differ). HEAD is routed to GET.
///
/// Not thread-safe while routes are added; match() may be called from any number of threads once
/// the router is built.
class Router {
 public:
  /// Throws core::Error(InvalidArgument) on a malformed pattern (no leading '/', empty segment,
  /// two parameters in a segment, a parameter name not [A-Za-z0-9_]+ or used twice), on Head,
  /// Options or Other (they are implied), or when (method, pattern) is routed already.
  /// `inlineHandler`, when given, answers what it can on the network thread (see InlineHandler).
  void add(Method method, std::string_view pattern, Handler handler,
           InlineHandler inlineHandler = {});

  /// Matches a percent-encoded path (no query).
  RouteMatch match(Method method, std::string_view path) const;

  std::size_t size() const { return routes_.size(); }

 private:
  struct Segment {
    std::string prefix;  // the literal, or the text before "{"
    std::string param;   // empty for a literal
    std::string suffix;  // text after "}"
    bool tail = false;   // "{name...}": the rest of the path
  };
  struct Entry {
    Route route;
    std::vector<Segment> segments;
  };
  /// Params and per-segment specificity (2 literal, 1 affixed parameter, 0 bare) when `entry`
  /// matches the decoded segments.
  static bool matches(const Entry& entry, const std::vector<std::string>& segments,
                      std::map<std::string, std::string, std::less<>>* params,
                      std::vector<int>* specificity);

  std::vector<std::unique_ptr<Entry>> routes_;  // stable addresses: RouteMatch points into them
};

}  // namespace vsm::server::http
