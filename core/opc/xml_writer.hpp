#pragma once

#include <cstddef>
#include <string>
#include <string_view>
#include <vector>

namespace vsm::core::detail {

/// Writes an XML document in one pass into a string, as pugixml's indented save lays it out (two
/// spaces per level, `<a />` for an element without content, `<a>text</a>` for one with text
/// only), without building a document tree: the hierarchy of a model of 10^5 patches is written
/// in a tenth of the time and memory a DOM takes. Text is escaped as pugixml escapes it (`&`, `<`,
/// `>`, and control characters as `&#NN;`).
class XmlWriter {
 public:
  /// Starts the document with `<?xml version="1.0" encoding="utf-8"?>`.
  XmlWriter();
  /// A fragment: elements laid out as inside `depth` open elements of a document (depth()), for
  /// the content of an element cut() left open. No declaration.
  explicit XmlWriter(std::size_t depth);

  /// Opens element `name`; its content follows until the matching close(). An element opened
  /// `oneLine` is written on one line with everything in it (`<item><key>a</key>...</item>`, as
  /// OPC.md lays out the hierarchy's items: 40% of a large hierarchy file is indentation else).
  void open(std::string_view name, bool oneLine = false);
  /// Closes the element opened last.
  void close();
  /// An element holding only `text`.
  void text(std::string_view name, std::string_view text);
  /// An element without content.
  void empty(std::string_view name);

  /// Ends the open start tag and hands out what is written so far; what follows (fragments made
  /// at depth(), then the rest of this writer) continues it.
  std::string cut();
  /// The number of elements open, with a fragment's enclosing ones.
  std::size_t depth() const { return depth_ + open_.size(); }

  /// Closes every element still open and returns the document.
  std::string finish() &&;

 private:
  void startLine();
  void endStartTag();
  /// Inside an element opened oneLine.
  bool inlined() const { return inlineFrom_ != 0; }
  /// Ends a line unless inlined().
  void endLine();

  std::string out_;
  std::size_t depth_ = 0;  // a fragment's enclosing elements
  std::vector<std::string> open_;
  /// The last open element's start tag is not yet ended (it may end as `<a />`).
  bool startTagOpen_ = false;
  /// open_.size() just after the outermost element opened oneLine was opened; 0: none is open.
  std::size_t inlineFrom_ = 0;
};

}  // namespace vsm::core::detail
