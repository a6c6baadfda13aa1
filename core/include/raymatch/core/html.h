#pragma once
// Helpers for self-contained HTML reports.
#include <string>

namespace raymatch {

/// Standard base64 (RFC 4648) of arbitrary bytes.
std::string Base64(const std::string& bytes);

/// A file's bytes; empty when it cannot be read.
std::string ReadFileBytes(const std::string& path);

/// An <img> tag embedding a PNG file as a data URI, with `alt` text (HTML-escaped here).
std::string EmbeddedPng(const std::string& png_path, const std::string& alt = "");

/// `text` with &, <, >, ' and " replaced by HTML entities.
std::string HtmlEscape(const std::string& text);

}  // namespace raymatch
