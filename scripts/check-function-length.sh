#!/bin/bash
# Checks that no function in the libraries that carry the physics and the estimator (simulate/,
# fit/, pipeline/) runs over 150 lines: a long function is where a stage's logic ends up written
# twice. A definition is a line at column 0 that opens a function (a name and '(' before any
# ';') with its '{' at the end of that line or a following one; it ends at the next line that
# starts with '}'. Lambdas count towards the function they sit in. Run by CI as the ctest
# `check_function_length`.
#   scripts/check-function-length.sh [FILE...]   # default: simulate/, fit/, pipeline/ sources
set -euo pipefail
cd "$(dirname "$0")/.."
limit=150
files=("$@")
if [ ${#files[@]} -eq 0 ]; then
  mapfile -t files < <(find simulate fit pipeline -path '*/src/*' \( -name '*.cpp' -o -name '*.h' \) \
    -type f | sort)
fi
awk -v limit="$limit" '
  FNR == 1 { state = 0 }
  # Looking for a definition: a name and an opening parenthesis at column 0.
  state == 0 && /^[A-Za-z_][A-Za-z0-9_:<>,*& ~]*[A-Za-z0-9_>*&] +[A-Za-z_~][A-Za-z0-9_:~]*\(/ &&
      !/;[ \t]*$/ {
    start = FNR; name = $0; state = 1
  }
  # Its signature: until a line that ends with "{" (the body) or ";" (a declaration).
  state == 1 {
    if ($0 ~ /;[ \t]*$/ && $0 !~ /\{/) { state = 0; next }
    if ($0 ~ /\{[ \t]*$/ && $0 !~ /\};[ \t]*$/) { state = 2; next }
    next
  }
  state == 2 && /^}/ {
    n = FNR - start + 1
    if (n > limit) {
      printf "%s:%d: %d lines (at most %d): %s\n", FILENAME, start, n, limit, substr(name, 1, 80)
      bad++
    }
    state = 0
  }
  END {
    if (bad) exit 1
  }
' "${files[@]}" || { echo "check-function-length: split the functions above" >&2; exit 1; }
echo "check-function-length: ${#files[@]} files, no function over $limit lines"
