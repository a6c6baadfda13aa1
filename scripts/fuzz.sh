#!/usr/bin/env bash
# Short libFuzzer run of every parser harness in fuzz/: builds them with clang,
# AddressSanitizer and UndefinedBehaviorSanitizer into build/fuzz/, then fuzzes each for
# FUZZ_SECONDS (default 60) starting from a copy of its committed corpus fuzz/corpus/<parser>/.
# New inputs go to build/fuzz/corpus/<parser>/, crashes to build/fuzz/artifacts/ (copy a crash
# into fuzz/corpus/<parser>/ once fixed: the normal test set replays that corpus).
# Usage: scripts/fuzz.sh [parser...]        (default: all; RAYMATCH_JOBS build jobs, default 1)
set -euo pipefail
cd "$(dirname "$0")/.."
parsers=("$@")
if ((${#parsers[@]} == 0)); then parsers=(scene calibration npy pipeline fit metadata zemax stack mesh); fi
cmake -S . -B build/fuzz -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
  -DCMAKE_C_COMPILER=clang -DCMAKE_CXX_COMPILER=clang++ \
  -DCMAKE_CXX_FLAGS="-fsanitize=address,undefined,fuzzer-no-link -fno-sanitize-recover=undefined -fno-omit-frame-pointer" \
  -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O1 -g" \
  -DRAYMATCH_FUZZ=ON -DRAYMATCH_BUILD_TESTS=OFF -DRAYMATCH_BUILD_BENCH=OFF >/dev/null
targets=()
for p in "${parsers[@]}"; do targets+=("fuzz_$p"); done
cmake --build build/fuzz -j "${RAYMATCH_JOBS:-1}" --target "${targets[@]}"
mkdir -p build/fuzz/artifacts
export ASAN_OPTIONS="detect_leaks=1:halt_on_error=1"
export UBSAN_OPTIONS="halt_on_error=1:print_stacktrace=1"
# The same LeakSanitizer suppressions as check-sanitizers.sh (Debian libraries only, each with
# its reason).
export LSAN_OPTIONS="suppressions=$PWD/scripts/lsan-suppressions.txt:print_suppressions=0"
for p in "${parsers[@]}"; do
  work=build/fuzz/corpus/$p
  mkdir -p "$work"
  cp -n fuzz/corpus/"$p"/* "$work"/ 2>/dev/null || true
  echo "== fuzzing $p for ${FUZZ_SECONDS:-60} s"
  build/fuzz/fuzz/fuzz_"$p" "$work" -max_total_time="${FUZZ_SECONDS:-60}" -timeout=10 \
    -rss_limit_mb=2048 -max_len=65536 -print_final_stats=1 \
    -artifact_prefix=build/fuzz/artifacts/"$p"- 2>&1 | tail -n 40
done
