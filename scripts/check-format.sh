#!/bin/bash
# Checks that the C++ sources follow .clang-format (Debian's clang-format 14), without changing
# them, after scripts/check-comments.sh (no issue numbers, dates, timings or outside files in
# the libraries' comments). Run by CI as the ctest `check_format`.
#   scripts/check-format.sh [FILE...]    # default: every C and C++ file git tracks
# Fix a file with: clang-format -i FILE   (the whole tree: scripts/check-format.sh --fix)
set -euo pipefail
cd "$(dirname "$0")/.."
fix=0
[ $# -gt 0 ] || scripts/check-comments.sh
if [ "${1:-}" = "--fix" ]; then fix=1; shift; fi
files=("$@")
if [ ${#files[@]} -eq 0 ]; then
  if git rev-parse --is-inside-work-tree >/dev/null 2>&1; then
    mapfile -t files < <(git ls-files '*.c' '*.cc' '*.cpp' '*.h' '*.hpp')
  else  # an exported tree without .git: the same suffixes, build folders left out
    mapfile -t files < <(find . -path ./build -prune -o -path ./out -prune -o \
      \( -name '*.c' -o -name '*.cc' -o -name '*.cpp' -o -name '*.h' -o -name '*.hpp' \) \
      -type f -print | sed 's|^\./||' | sort)
  fi
fi
# Exit 77 (ctest: skipped) without clang-format, or with another major version than the files
# were formatted with (14, Debian 12): other versions break lines differently.
command -v clang-format >/dev/null || { echo "check-format: skipped: clang-format not installed (apt-get install clang-format)" >&2; exit 77; }
major=$(clang-format --version | sed -n 's/.*version \([0-9]*\).*/\1/p')
[ "$major" = 14 ] || { echo "check-format: skipped: clang-format $major, the files follow version 14" >&2; exit 77; }
if [ $fix -eq 1 ]; then
  clang-format -i "${files[@]}"
  echo "check-format: formatted ${#files[@]} files"
  exit 0
fi
if clang-format --dry-run --Werror "${files[@]}" 2>/dev/null; then
  echo "check-format: ${#files[@]} files conform to .clang-format"
  exit 0
fi
for f in "${files[@]}"; do  # name the ones that do not
  clang-format --dry-run --Werror "$f" 2>/dev/null ||
    echo "check-format: $f is not formatted (clang-format -i $f)" >&2
done
exit 1
