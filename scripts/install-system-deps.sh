#!/usr/bin/env bash
# Set-up step 1 of 2: the system libraries ComReg needs on Debian/Ubuntu.
#   - Mesa EGL and OSMesa: off-screen rendering with VTK (screenshots, reports, headless tests)
#   - libusb-1.0-0: needed by `import open3d` (the RANSAC baseline)
#   - python3-venv: to create the project's virtual environment
# Runs apt-get as root, through sudo when started as another user.
set -euo pipefail

packages=(libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 libusb-1.0-0 python3-venv)

if [ "$(id -u)" -eq 0 ]; then
  as_root=()
elif command -v sudo >/dev/null 2>&1; then
  as_root=(sudo)
else
  echo "error: installing system packages needs root; run this script as root or install sudo." >&2
  exit 2
fi

if ! command -v apt-get >/dev/null 2>&1; then
  echo "error: apt-get not found. On a non-Debian system install the equivalents of:" >&2
  echo "  ${packages[*]}" >&2
  exit 2
fi

missing=()
for pkg in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if [ ${#missing[@]} -eq 0 ]; then
  echo "System packages already installed: ${packages[*]}"
  exit 0
fi
echo "Installing: ${missing[*]}"
"${as_root[@]}" apt-get update -qq
DEBIAN_FRONTEND=noninteractive "${as_root[@]}" apt-get install -y -qq --no-install-recommends "${missing[@]}"
