#include "server/http/router.hpp"

#include <algorithm>
#include <set>

#include "core/common/error.hpp"

namespace vsm::server::http {

using core::Error;
using core::ErrorCode;

namespace {

std::vector<std::string_view> split(std::string_view path) {
  std::vector<std::string_view> out;
  path.remove_prefix(1);  // the leading '/'
  for (;;) {
    const std::size_t slash = path.find('/');
    out.push_back(path.substr(0, slash));
    if (slash == std::string_view::npos) {
      return out;
    }
    path.remove_prefix(slash + 1);
  }
}

bool isNameChar(char c) {
  return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_';
}

}  // namespace

void Router::add(Method method, std::string_view pattern, Handler handler,
                 InlineHandler inlineHandler) {
  const auto bad = [&](std::string_view why) {
    throw Error(ErrorCode::InvalidArgument,
                "route pattern '" + std::string(pattern) + "': " + std::string(why));
  };
  if (method == Method::Head || method == Method::Options || method == Method::Other) {
    bad("HEAD and OPTIONS are implied; other methods cannot be routed");
  }
  if (!pattern.starts_with("/")) {
    bad("must start with '/'");
  }
  auto entry = std::make_unique<Entry>();
  std::set<std::string, std::less<>> names;
  const std::vector<std::string_view> texts = split(pattern);
  for (std::size_t i = 0; i < texts.size(); ++i) {
    const std::string_view text = texts[i];
    if (text.empty() && pattern != "/") {
      bad("empty segment");
    }
    Segment segment;
    const std::size_t open = text.find('{');
    if (open == std::string_view::npos) {
      if (text.find('}') != std::string_view::npos) {
        bad("unbalanced '}'");
      }
      segment.prefix = text;
    } else {
      const std::size_t close = text.find('}', open);
      if (close == std::string_view::npos) {
        bad("unbalanced '{'");
      }
      std::string_view name = text.substr(open + 1, close - open - 1);
      if (name.ends_with("...")) {
        if (i + 1 != texts.size() || open != 0 || close + 1 != text.size()) {
          bad("a tail parameter '{name...}' is a whole last segment");
        }
        name.remove_suffix(3);
        segment.tail = true;
      }
      if (name.empty() || !std::all_of(name.begin(), name.end(), isNameChar)) {
        bad("parameter names are [A-Za-z0-9_]+");
      }
      const std::string_view suffix = text.substr(close + 1);
      if (suffix.find_first_of("{}") != std::string_view::npos) {
        bad("one parameter per segment");
      }
      if (!names.emplace(name).second) {
        bad("parameter '" + std::string(name) + "' used twice");
      }
      segment.prefix = text.substr(0, open);
      segment.param = name;
      segment.suffix = suffix;
    }
    entry->segments.push_back(std::move(segment));
  }
  for (const auto& existing : routes_) {
    if (existing->route.method == method && existing->route.pattern == pattern) {
      bad(std::string(toString(method)) + " is routed already");
    }
  }
  entry->route = Route{method, std::string(pattern), std::move(handler), std::move(inlineHandler)};
  routes_.push_back(std::move(entry));
}

bool Router::matches(const Entry& entry, const std::vector<std::string>& segments,
                     std::map<std::string, std::string, std::less<>>* params,
                     std::vector<int>* specificity) {
  const bool tail = !entry.segments.empty() && entry.segments.back().tail;
  if (tail ? segments.size() + 1 < entry.segments.size()
           : entry.segments.size() != segments.size()) {
    return false;
  }
  params->clear();
  specificity->clear();
  for (std::size_t i = 0; i < entry.segments.size(); ++i) {
    const Segment& s = entry.segments[i];
    if (s.tail) {
      std::string rest;
      for (std::size_t j = i; j < segments.size(); ++j) {
        rest += (j == i ? "" : "/") + segments[j];
      }
      (*params)[s.param] = std::move(rest);
      specificity->push_back(-1);
      break;
    }
    const std::string& text = segments[i];
    if (s.param.empty()) {
      if (text != s.prefix) {
        return false;
      }
      specificity->push_back(2);
      continue;
    }
    if (text.size() <= s.prefix.size() + s.suffix.size() || !text.starts_with(s.prefix) ||
        !text.ends_with(s.suffix)) {
      return false;
    }
    (*params)[s.param] =
        text.substr(s.prefix.size(), text.size() - s.prefix.size() - s.suffix.size());
    specificity->push_back(s.prefix.empty() && s.suffix.empty() ? 0 : 1);
  }
  return true;
}

RouteMatch Router::match(Method method, std::string_view path) const {
  RouteMatch out;
  if (!path.starts_with("/")) {
    return out;
  }
  std::vector<std::string> segments;
  for (const std::string_view raw : split(path)) {
    auto decoded = percentDecode(raw, false);
    if (!decoded) {
      return out;  // a malformed escape names no resource
    }
    segments.push_back(std::move(*decoded));
  }

  const Method wanted = method == Method::Head ? Method::Get : method;
  std::map<std::string, std::string, std::less<>> params;
  std::vector<int> specificity;
  std::vector<int> best;
  std::set<Method> allowed;
  for (const auto& entry : routes_) {
    if (!matches(*entry, segments, &params, &specificity)) {
      continue;
    }
    allowed.insert(entry->route.method);
    if (entry->route.method == wanted && (out.route == nullptr || specificity > best)) {
      out.route = &entry->route;
      out.params = params;
      best = specificity;
    }
  }
  if (allowed.empty()) {
    return out;
  }
  out.kind = out.route != nullptr ? RouteMatch::Kind::Found : RouteMatch::Kind::MethodNotAllowed;
  if (allowed.contains(Method::Get)) {
    allowed.insert(Method::Head);
  }
  allowed.insert(Method::Options);
  out.allowed.assign(allowed.begin(), allowed.end());
  return out;
}

}  // namespace vsm::server::http
