#pragma once
// Strict TOML reading: typed getters that report file:line:col and what was expected, and a
// check that every key in a table was used (unknown keys are errors, pbrt ReportUnused style).
#include <toml++/toml.h>

#include <array>
#include <functional>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "raymatch/core/error.h"

namespace raymatch {

/// Parses a TOML file; throws Error with the parser's line/column on syntax errors and a clear
/// message when the file cannot be opened.
toml::table ParseTomlFile(const std::string& path);

/// Parses TOML text (e.g. a scene passed as a string from Python); `source_name` stands for the
/// file in messages ("source_name:line:col: error: TOML syntax: ...").
toml::table ParseTomlString(const std::string& text, const std::string& source_name);

/// A view of one TOML table that records which keys were read. Call Finish() after reading to
/// turn any unread key into an "unknown key" error listing the accepted keys.
class TomlReader {
 public:
  TomlReader(const toml::table& table, std::string file, std::string path_prefix);

  bool Has(const std::string& key) const;
  FileLocation Where() const;                        ///< Location of the table itself.
  FileLocation Where(const std::string& key) const;  ///< Location of a key's value.
  std::string Path(const std::string& key) const;    ///< "section.key" for messages.
  [[noreturn]] void Fail(const std::string& key, const std::string& message) const;

  double Number(const std::string& key);                     ///< Required number.
  double Number(const std::string& key, double fallback);    ///< Optional number.
  double Positive(const std::string& key);                   ///< Required, > 0.
  double Positive(const std::string& key, double fallback);  ///< Optional, > 0.
  double InRange(const std::string& key, double lo, double hi, double fallback,
                 bool lo_open = false, bool hi_open = false);  ///< Optional, in [lo, hi].
  int64_t Integer(const std::string& key, int64_t fallback, int64_t lo, int64_t hi);
  bool Bool(const std::string& key, bool fallback);
  std::string String(const std::string& key);  ///< Required string.
  std::string String(const std::string& key, const std::string& fallback);
  /// Required string that must be one of `choices`.
  std::string Choice(const std::string& key, const std::vector<std::string>& choices,
                     std::optional<std::string> fallback = std::nullopt);
  std::vector<double> Numbers(const std::string& key, size_t min_size = 1,
                              size_t max_size = SIZE_MAX);   ///< Required array.
  std::vector<std::string> Strings(const std::string& key);  ///< Required, non-empty.
  /// Required array of arrays of `cols` numbers each, e.g. [[r, z], [r, z], ...].
  std::vector<std::vector<double>> NumberRows(const std::string& key, size_t cols);
  std::array<double, 3> Vec3(const std::string& key, std::array<double, 3> fallback);
  std::array<double, 3> Vec3(const std::string& key);
  /// A sub-table; marks the key used.
  TomlReader Table(const std::string& key);
  /// An array of tables ([[key]]); empty when absent.
  std::vector<TomlReader> Tables(const std::string& key);

  /// Throws for the first key that was never read.
  void Finish() const;
  const std::string& file() const { return file_; }

 private:
  const toml::node* Node(const std::string& key) const;
  [[noreturn]] void TypeError(const std::string& key, const std::string& expected) const;

  const toml::table* table_;
  std::string file_;
  std::string prefix_;
  mutable std::set<std::string> used_;
};

}  // namespace raymatch
