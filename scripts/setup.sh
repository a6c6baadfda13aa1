#!/usr/bin/env bash
# Installs raymatch's Debian build dependencies when missing, then configures and builds.
# Usage: scripts/setup.sh            (release build in build/release)
# Re-running is cheap: installed packages are skipped and the build is incremental.
set -euo pipefail
cd "$(dirname "$0")/.."

PACKAGES=(
  build-essential cmake ninja-build pkg-config
  libembree-dev libtbb-dev libcli11-dev libtomlplusplus-dev
  libeigen3-dev nlohmann-json3-dev librandom123-dev libassimp-dev libhdf5-dev libhwy-dev
  libtiff-dev libpng-dev libopenexr-dev  # image files
  libopencv-dev
  libopenvdb-dev  # iso-surfaces of volume-fraction grids
  libceres-dev  # calibration fits
  libboost-dev  # Boost.Math's monotone interpolation (fit's profile likelihood)
  clang-format  # the check_format test (Debian 12: clang-format 14)
  libmrcal-dev  # light field from mrcal .cameramodel files (optional in CMake)
  libopenmpi-dev openmpi-bin  # MPI across machines (optional in CMake: RAYMATCH_MPI)
  libcamera-dev  # capture from libcamera cameras (optional in CMake: RAYMATCH_WITH_LIBCAMERA)
  libgtest-dev libgmock-dev libbenchmark-dev
  python3 python3-numpy python3-scipy python3-skimage python3-tifffile  # test references
  pybind11-dev python3-dev python3-pytest  # the Python module (RAYMATCH_PYTHON) and its tests
  libplplot-dev plplot-driver-cairo fonts-dejavu-core  # report figures (docs/figures.md)
  chromium  # report_browser test: reports opened in headless Chromium (skipped without it)
)

missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "raymatch setup: installing ${missing[*]}" >&2
  SUDO=""
  if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
  export DEBIAN_FRONTEND=noninteractive
  $SUDO apt-get update -q
  $SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
fi

cmake --preset release >/dev/null
# Two cores on the reference machine; more jobs only thrash memory on the heavy TUs.
cmake --build --preset release -j "${RAYMATCH_JOBS:-$(nproc)}"
