#!/bin/sh
# Debian packages tumor3d needs outside Python: Open3D's offscreen renderer
# (libusb, Vulkan loader, Mesa's Vulkan drivers) and headless Chromium, with
# which the tests check that viewer.html and report.html load and show the
# mesh. Installed when running as root and missing; otherwise a clear message
# names them. (The default renderer, numpy/numba, needs none of them.)
set -eu
PKGS="libusb-1.0-0 libvulkan1 mesa-vulkan-drivers chromium"
missing=""
for p in $PKGS; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
[ -z "$missing" ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
    echo "tumor3d: missing system packages:$missing (libusb-1.0, Vulkan loader and Mesa Vulkan drivers for Open3D; chromium for the browser tests); install them with your package manager." >&2
    exit 1
fi
if [ "$(id -u)" -ne 0 ]; then
    echo "tumor3d: missing Debian packages:$missing (Open3D rendering; chromium for the browser tests)" >&2
    echo "         install them with: sudo apt-get install -y --no-install-recommends$missing" >&2
    exit 1
fi
echo "tumor3d: installing Debian packages:$missing"
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq >/dev/null
apt-get install -y -qq --no-install-recommends $missing >/dev/null
