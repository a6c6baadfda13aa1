#!/bin/sh
# ctest entry point (python/CMakeLists.txt): runs python/tests with the given interpreter;
# exit 77 (ctest: skipped) when pytest is not installed (Debian python3-pytest).
PY="$1"
if ! "$PY" -c "import pytest" 2>/dev/null; then
  echo "python_module: skipped: pytest not installed for $PY (apt-get install python3-pytest)"
  exit 77
fi
exec "$PY" -m pytest -q -p no:cacheprovider "$(dirname "$0")"
