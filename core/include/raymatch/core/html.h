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

/// An uncertainty to two significant digits ("0.0019"); "not computed" where it is not a
/// positive finite number (a quantity that was not determined is not 0).
std::string FormatUncertainty(double uncertainty);

/// `value` to the decimal place of its uncertainty's second significant digit (1.29947 with
/// 0.00190911: "1.2995"); to `digits` significant digits where the uncertainty is not a positive
/// finite number.
std::string FormatValue(double value, double uncertainty, int digits = 6);

}  // namespace raymatch
