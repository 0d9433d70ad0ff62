#!/usr/bin/env bash
# Installs what CortexFuse needs to build, run and test, from Debian 12's packages.
# Idempotent: when everything is there it only checks, quickly.
set -euo pipefail
PACKAGES=(
  build-essential cmake ninja-build pkg-config
  libinsighttoolkit5-dev libvtk9-dev libopencv-dev libeigen3-dev
  libnlopt-cxx-dev libnlopt-dev libtbb-dev zlib1g-dev
  nlohmann-json3-dev libcli11-dev libspdlog-dev
  libgtest-dev libgmock-dev libbenchmark-dev
  elastix time
  python3-nibabel python3-scipy python3-pil
  clang
  libgphoto2-dev libraw-dev libv4l-dev libudev-dev umockdev libumockdev-dev
  libegl-dev libepoxy-dev libegl-mesa0 libgl1-mesa-dri
  xvfb xauth jq curl
  ccache lld
  libcivetweb-dev libcivetweb1 libcpp-httplib-dev libsystemd-dev systemd
  libsqlite3-dev sqlite3 libsodium-dev libzip-dev
  chromium
  cage xwayland grim
)
missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "setup: installing ${missing[*]}" >&2
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO=sudo
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
fi
# The web UI (ui/) builds with node + npm; Debian 12's nodejs 18 / npm 9 are enough (Vite 6).
# Only when there is no node at all, so a newer node already on the machine is left alone.
if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
  echo "setup: installing nodejs npm" >&2
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO=sudo
  $SUDO apt-get update -q
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends nodejs npm
fi
