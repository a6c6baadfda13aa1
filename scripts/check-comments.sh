#!/bin/bash
# Library code says what holds now; its history belongs in git. Fails on, in the libraries'
# sources (apps core simulate calibrate compare fit capture pipeline python; tests, benchmarks
# and docs may cite them):
#   - issue numbers ("issue 26"): an issue is closed and renumbered long before the code goes,
#   - dates (2026-11-25): a date says when, not what,
#   - measured timings ("took 12 s", "3x faster", "measured ... 0.5 s"): they go stale with the
#     next machine or compiler; they belong in bench/ and docs/performance.md,
#   - files outside the repository (REFERENCE.md, docs/optics.md): cite the source by its name.
# Run by CI through scripts/check-format.sh (the ctest `check_format`).
#   scripts/check-comments.sh [FILE...]    # default: the libraries' files git tracks
set -euo pipefail
cd "$(dirname "$0")/.."
files=("$@")
if [ ${#files[@]} -eq 0 ]; then
  dirs=(apps core simulate calibrate compare fit capture pipeline python)
  if git rev-parse --is-inside-work-tree >/dev/null 2>&1; then
    mapfile -t files < <(git ls-files "${dirs[@]}" | grep -v '^python/tests/')
  else
    mapfile -t files < <(find "${dirs[@]}" -type f ! -path 'python/tests/*' | sort)
  fi
fi
patterns=(
  '[Ii]ssues? ?#?[0-9]+'
  '\b20[0-9]{2}-[01][0-9]-[0-3][0-9]\b'
  'REFERENCE\.md|docs/optics\.md'
  '(took|measured|faster|slower|speed-?up)[^"]*\b[0-9.]+ ?(ms|s|min|minutes|seconds)\b'
  '\b[0-9.]+ ?(ms|s|min|minutes|seconds)\b[^"]*(faster|slower|instead of)'
  '\b[0-9.]+ ?x (faster|slower)'
)
bad=0
for p in "${patterns[@]}"; do
  if grep -nHE "$p" "${files[@]}"; then bad=1; fi
done
# Docs, tests and benchmarks may cite issues and measurements, but not files a user does not
# have: the whole repository's text (the check's own fixture aside), when no files were named.
if [ "$#" -eq 0 ] && git rev-parse --is-inside-work-tree >/dev/null 2>&1; then
  mapfile -t others < <(git ls-files README.md docs tests bench tools datasets-sample |
    grep -v '^tests/testing/bad_comments.txt$')
  if grep -nHE 'REFERENCE\.md|docs/optics\.md' "${others[@]}"; then bad=1; fi
fi
if [ $bad -ne 0 ]; then
  echo "check-comments: the lines above carry an issue number, a date, a measured timing or a file" \
    "outside the repository (scripts/check-comments.sh says why not)" >&2
  exit 1
fi
echo "check-comments: ${#files[@]} files: no issue numbers, dates, timings or outside files"
