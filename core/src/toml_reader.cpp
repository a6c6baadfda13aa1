#include "raymatch/core/toml_reader.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <vector>

namespace raymatch {

toml::table ParseTomlFile(const std::string& path) {
  std::error_code ec;
  if (std::filesystem::is_directory(path, ec))
    throw Error(FileLocation{path}, "is a folder, not a TOML file");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(FileLocation{path}, "cannot open file for reading");
  std::stringstream ss;
  ss << in.rdbuf();
  return ParseTomlString(ss.str(), path);
}

toml::table ParseTomlString(const std::string& text, const std::string& source_name) {
  try {
    return toml::parse(text, source_name);
  } catch (const toml::parse_error& e) {
    const auto& b = e.source().begin;
    throw Error(FileLocation{source_name, static_cast<int>(b.line), static_cast<int>(b.column)},
                std::string("TOML syntax: ") + std::string(e.description()));
  }
}

static std::string Num(double v) {
  std::ostringstream os;
  os.precision(10);
  os << v;
  return os.str();
}

static FileLocation LocOf(const std::string& file, const toml::source_region& r) {
  return FileLocation{file, static_cast<int>(r.begin.line), static_cast<int>(r.begin.column)};
}

static const char* TypeName(const toml::node& n) {
  switch (n.type()) {
    case toml::node_type::table:
      return "a table";
    case toml::node_type::array:
      return "an array";
    case toml::node_type::string:
      return "a string";
    case toml::node_type::integer:
      return "an integer";
    case toml::node_type::floating_point:
      return "a number";
    case toml::node_type::boolean:
      return "a boolean";
    default:
      return "a date/time";
  }
}

/// Edit distance (insertions, deletions, substitutions, adjacent transpositions: the optimal
/// string alignment distance) between two keys, for "did you mean" hints.
static size_t KeyDistance(const std::string& a, const std::string& b) {
  std::vector<std::vector<size_t>> d(a.size() + 1, std::vector<size_t>(b.size() + 1));
  for (size_t i = 0; i <= a.size(); ++i) d[i][0] = i;
  for (size_t j = 0; j <= b.size(); ++j) d[0][j] = j;
  for (size_t i = 1; i <= a.size(); ++i)
    for (size_t j = 1; j <= b.size(); ++j) {
      d[i][j] = std::min(
          {d[i - 1][j] + 1, d[i][j - 1] + 1, d[i - 1][j - 1] + (a[i - 1] == b[j - 1] ? 0 : 1)});
      if (i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1])
        d[i][j] = std::min(d[i][j], d[i - 2][j - 2] + 1);
    }
  return d[a.size()][b.size()];
}

/// The edit distance from `written` to `want` when it is close enough to be a misspelling (at
/// most 2 edits, and fewer than a third of the longer key's letters); 0 otherwise.
static size_t MisspellingDistance(const std::string& written, const std::string& want) {
  const size_t d = KeyDistance(written, want);
  return d <= 2 && 3 * d < std::max(written.size(), want.size()) ? d : 0;
}

TomlReader::TomlReader(const toml::table& table, std::string file, std::string path_prefix)
    : table_(&table), file_(std::move(file)), prefix_(std::move(path_prefix)) {}

bool TomlReader::Has(const std::string& key) const { return table_->contains(key); }

const toml::node* TomlReader::Node(const std::string& key) const {
  used_.insert(key);
  return table_->get(key);
}

FileLocation TomlReader::Where() const { return LocOf(file_, table_->source()); }

FileLocation TomlReader::Where(const std::string& key) const {
  if (const toml::node* n = table_->get(key)) return LocOf(file_, n->source());
  return Where();
}

std::string TomlReader::Path(const std::string& key) const {
  return prefix_.empty() ? key : prefix_ + "." + key;
}

void TomlReader::Fail(const std::string& key, const std::string& message) const {
  throw Error(Where(key), "'" + Path(key) + "': " + message);
}

void TomlReader::TypeError(const std::string& key, const std::string& expected) const {
  const toml::node* n = table_->get(key);
  if (!n) {
    const std::string where = prefix_.empty() ? "at the top level" : "in [" + prefix_ + "]";
    // A key written in its place with a typo: name it, where it is written.
    for (const auto& [k, v] : *table_) {
      const std::string written(k.str());
      if (!used_.count(written) && MisspellingDistance(written, key) > 0)
        throw Error(LocOf(file_, k.source()), "missing required key '" + Path(key) + "' " + where +
                                                  "; found '" + Path(written) +
                                                  "': did you mean '" + key + "'? (expected " +
                                                  expected + ")");
    }
    throw Error(Where(), "missing required key '" + Path(key) + "' " + where + " (expected " +
                             expected + ")");
  }
  throw Error(Where(key), "'" + Path(key) + "': expected " + expected + ", got " + TypeName(*n));
}

double TomlReader::Number(const std::string& key) {
  const toml::node* n = Node(key);
  if (!n || !(n->is_integer() || n->is_floating_point())) TypeError(key, "a number");
  const double v =
      n->is_integer() ? static_cast<double>(n->as_integer()->get()) : n->as_floating_point()->get();
  if (!std::isfinite(v)) Fail(key, "expected a finite number");
  return v;
}

double TomlReader::Number(const std::string& key, double fallback) {
  return Has(key) ? Number(key) : (used_.insert(key), fallback);
}

double TomlReader::Positive(const std::string& key) {
  const double v = Number(key);
  if (!(v > 0)) Fail(key, "expected a positive number, got " + Num(v));
  return v;
}

double TomlReader::Positive(const std::string& key, double fallback) {
  return Has(key) ? Positive(key) : (used_.insert(key), fallback);
}

double TomlReader::InRange(const std::string& key, double lo, double hi, double fallback,
                           bool lo_open, bool hi_open) {
  if (!Has(key)) {
    used_.insert(key);
    return fallback;
  }
  const double v = Number(key);
  const bool ok = (lo_open ? v > lo : v >= lo) && (hi_open ? v < hi : v <= hi);
  if (!ok) {
    std::ostringstream os;
    os << "expected a number in " << (lo_open ? "(" : "[") << lo << ", " << hi
       << (hi_open ? ")" : "]") << ", got " << v;
    Fail(key, os.str());
  }
  return v;
}

int64_t TomlReader::Integer(const std::string& key, int64_t fallback, int64_t lo, int64_t hi) {
  if (!Has(key)) {
    used_.insert(key);
    return fallback;
  }
  const toml::node* n = Node(key);
  int64_t v = 0;
  if (n->is_integer()) {
    v = n->as_integer()->get();
  } else if (n->is_floating_point() &&
             std::floor(n->as_floating_point()->get()) == n->as_floating_point()->get() &&
             std::abs(n->as_floating_point()->get()) < 9e18) {
    v = static_cast<int64_t>(n->as_floating_point()->get());  // allow 1e9 for ray counts
  } else {
    TypeError(key, "an integer");
  }
  if (v < lo || v > hi) {
    Fail(key, "expected an integer in [" + std::to_string(lo) + ", " + std::to_string(hi) +
                  "], got " + std::to_string(v));
  }
  return v;
}

bool TomlReader::Bool(const std::string& key, bool fallback) {
  if (!Has(key)) {
    used_.insert(key);
    return fallback;
  }
  const toml::node* n = Node(key);
  if (!n->is_boolean()) TypeError(key, "true or false");
  return n->as_boolean()->get();
}

std::string TomlReader::String(const std::string& key) {
  const toml::node* n = Node(key);
  if (!n || !n->is_string()) TypeError(key, "a string");
  return n->as_string()->get();
}

std::string TomlReader::String(const std::string& key, const std::string& fallback) {
  return Has(key) ? String(key) : (used_.insert(key), fallback);
}

std::string TomlReader::Choice(const std::string& key, const std::vector<std::string>& choices,
                               std::optional<std::string> fallback) {
  std::string list;
  for (const auto& c : choices) list += (list.empty() ? "\"" : ", \"") + c + "\"";
  if (!Has(key) && fallback) {
    used_.insert(key);
    return *fallback;
  }
  const toml::node* n = Node(key);
  if (!n || !n->is_string()) TypeError(key, "one of " + list);
  const std::string v = n->as_string()->get();
  for (const auto& c : choices)
    if (c == v) return v;
  Fail(key, "expected one of " + list + ", got \"" + v + "\"");
}

std::vector<std::string> TomlReader::Strings(const std::string& key) {
  const toml::node* n = Node(key);
  if (!n || !n->is_array()) TypeError(key, "an array of strings");
  std::vector<std::string> out;
  for (const toml::node& e : *n->as_array()) {
    if (!e.is_string())
      throw Error(LocOf(file_, e.source()),
                  "'" + Path(key) + "': expected an array of strings, found " + TypeName(e));
    out.push_back(e.as_string()->get());
  }
  if (out.empty()) Fail(key, "expected at least one string");
  return out;
}

std::vector<double> TomlReader::Numbers(const std::string& key, size_t min_size, size_t max_size) {
  const toml::node* n = Node(key);
  if (!n || !n->is_array()) TypeError(key, "an array of numbers");
  const toml::array& a = *n->as_array();
  std::vector<double> out;
  for (const toml::node& e : a) {
    if (!(e.is_integer() || e.is_floating_point()))
      throw Error(LocOf(file_, e.source()),
                  "'" + Path(key) + "': expected an array of numbers, found " + TypeName(e));
    const double v =
        e.is_integer() ? static_cast<double>(e.as_integer()->get()) : e.as_floating_point()->get();
    if (!std::isfinite(v))
      throw Error(LocOf(file_, e.source()), "'" + Path(key) + "': expected finite numbers");
    out.push_back(v);
  }
  if (out.size() < min_size || out.size() > max_size) {
    std::string expect = min_size == max_size ? std::to_string(min_size)
                         : max_size == SIZE_MAX
                             ? "at least " + std::to_string(min_size)
                             : std::to_string(min_size) + " to " + std::to_string(max_size);
    Fail(key, "expected " + expect + " numbers, got " + std::to_string(out.size()));
  }
  return out;
}

std::vector<std::vector<double>> TomlReader::NumberRows(const std::string& key, size_t cols) {
  const toml::node* n = Node(key);
  if (!n || !n->is_array()) TypeError(key, "an array of [" + std::to_string(cols) + " numbers]");
  std::vector<std::vector<double>> out;
  for (const toml::node& row : *n->as_array()) {
    const FileLocation where = LocOf(file_, row.source());
    if (!row.is_array() || row.as_array()->size() != cols)
      throw Error(where, "'" + Path(key) + "': each entry must be an array of " +
                             std::to_string(cols) + " numbers");
    std::vector<double> v;
    for (const toml::node& e : *row.as_array()) {
      if (!(e.is_integer() || e.is_floating_point()))
        throw Error(where, "'" + Path(key) + "': expected numbers, found " + TypeName(e));
      const double x =
          e.is_integer() ? double(e.as_integer()->get()) : e.as_floating_point()->get();
      if (!std::isfinite(x)) throw Error(where, "'" + Path(key) + "': expected finite numbers");
      v.push_back(x);
    }
    out.push_back(v);
  }
  return out;
}

std::array<double, 3> TomlReader::Vec3(const std::string& key) {
  const auto v = Numbers(key, 3, 3);
  return {v[0], v[1], v[2]};
}

std::array<double, 3> TomlReader::Vec3(const std::string& key, std::array<double, 3> fallback) {
  return Has(key) ? Vec3(key) : (used_.insert(key), fallback);
}

TomlReader TomlReader::Table(const std::string& key) {
  const toml::node* n = Node(key);
  if (!n || !n->is_table()) TypeError(key, "a table");
  return TomlReader(*n->as_table(), file_, Path(key));
}

std::vector<TomlReader> TomlReader::Tables(const std::string& key) {
  std::vector<TomlReader> out;
  const toml::node* n = Node(key);
  if (!n) return out;
  if (!n->is_array_of_tables()) TypeError(key, "an array of tables ([[" + key + "]])");
  int i = 0;
  for (const toml::node& e : *n->as_array())
    out.emplace_back(*e.as_table(), file_, Path(key) + "[" + std::to_string(i++) + "]");
  return out;
}

void TomlReader::Finish() const {
  for (const auto& [k, v] : *table_) {
    const std::string key(k.str());
    if (used_.count(key)) continue;
    std::string accepted, nearest;
    size_t best = SIZE_MAX;
    for (const auto& u : used_) {
      accepted += (accepted.empty() ? "" : ", ") + u;
      const size_t d = MisspellingDistance(key, u);
      if (d > 0 && d < best) best = d, nearest = u;
    }
    throw Error(LocOf(file_, k.source()),
                "unknown key '" + Path(key) + "'" +
                    (nearest.empty() ? "" : ": did you mean '" + nearest + "'?") +
                    (accepted.empty() ? "" : " (accepted here: " + accepted + ")"));
  }
}

}  // namespace raymatch
