// One-pass XML output in pugixml's indented layout, with elements on one line where asked.
#include "core/opc/xml_writer.hpp"

#include <cassert>
#include <utility>

namespace vsm::core::detail {
namespace {

void appendEscaped(std::string& out, std::string_view text) {
  for (const char c : text) {
    const auto u = static_cast<unsigned char>(c);
    if (c == '&') {
      out += "&amp;";
    } else if (c == '<') {
      out += "&lt;";
    } else if (c == '>') {
      out += "&gt;";
    } else if (u < 32 && c != '\t' && c != '\n' && c != '\r') {
      // NUL ends a pugixml text; the other control characters are written as pugixml does.
      if (c == '\0') {
        return;
      }
      out += "&#";
      out += static_cast<char>('0' + u / 10);
      out += static_cast<char>('0' + u % 10);
      out += ';';
    } else {
      out += c;
    }
  }
}

}  // namespace

XmlWriter::XmlWriter() : out_("<?xml version=\"1.0\" encoding=\"utf-8\"?>\n") {}

XmlWriter::XmlWriter(std::size_t depth) : depth_(depth) {}

void XmlWriter::startLine() {
  endStartTag();
  if (!inlined()) {
    out_.append(2 * depth(), ' ');
  }
}

void XmlWriter::endLine() {
  if (!inlined()) {
    out_ += '\n';
  }
}

std::string XmlWriter::cut() {
  endStartTag();
  return std::exchange(out_, {});
}

void XmlWriter::endStartTag() {
  if (startTagOpen_) {
    out_ += '>';
    endLine();
    startTagOpen_ = false;
  }
}

void XmlWriter::open(std::string_view name, bool oneLine) {
  startLine();
  out_ += '<';
  out_ += name;
  open_.emplace_back(name);
  startTagOpen_ = true;
  if (oneLine && !inlined()) {
    inlineFrom_ = open_.size();
  }
}

void XmlWriter::close() {
  assert(!open_.empty());
  const bool endsInline = open_.size() == inlineFrom_;
  std::string name = std::move(open_.back());
  open_.pop_back();
  if (startTagOpen_) {
    out_ += " />";
    startTagOpen_ = false;
  } else {
    if (!inlined()) {
      out_.append(2 * depth(), ' ');
    }
    out_ += "</";
    out_ += name;
    out_ += '>';
  }
  if (endsInline) {
    inlineFrom_ = 0;
  }
  endLine();
}

void XmlWriter::text(std::string_view name, std::string_view text) {
  startLine();
  out_ += '<';
  out_ += name;
  out_ += '>';
  appendEscaped(out_, text);
  out_ += "</";
  out_ += name;
  out_ += '>';
  endLine();
}

void XmlWriter::empty(std::string_view name) {
  startLine();
  out_ += '<';
  out_ += name;
  out_ += " />";
  endLine();
}

std::string XmlWriter::finish() && {
  while (!open_.empty()) {
    close();
  }
  return std::move(out_);
}

}  // namespace vsm::core::detail
