#!/bin/sh
# Debian packages Open3D's offscreen renderer needs. Installed when running as
# root and missing; otherwise a clear message names them.
set -eu
PKGS="libusb-1.0-0 libvulkan1 mesa-vulkan-drivers"
missing=""
for p in $PKGS; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
[ -z "$missing" ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
    echo "tumor3d: Open3D rendering needs the system libraries:$missing (libusb-1.0, Vulkan loader, Mesa Vulkan drivers); install them with your package manager." >&2
    exit 1
fi
if [ "$(id -u)" -ne 0 ]; then
    echo "tumor3d: missing Debian packages needed by Open3D:$missing" >&2
    echo "         install them with: sudo apt-get install -y --no-install-recommends$missing" >&2
    exit 1
fi
echo "tumor3d: installing Debian packages for Open3D:$missing"
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq >/dev/null
apt-get install -y -qq --no-install-recommends $missing >/dev/null
