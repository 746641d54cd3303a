#!/usr/bin/env bash
# Build the image's base without an image registry: debootstrap a Debian bookworm root file
# system with Python 3.11 and the shared libraries the wheels need, then `docker import` it.
#
#   docker/build_base_image.sh [TAG]        (default TAG: robonav-base:bookworm; needs root)
#
# Packages come from the Debian mirror the host's apt uses (or DEBIAN_MIRROR), so an
# air-gapped cell with a local mirror builds the same way.
set -euo pipefail

tag=${1:-robonav-base:bookworm}
suite=bookworm
# python3-venv: the image's virtual environment; libgomp1, libusb-1.0-0, libgl1, libegl1:
# loaded by open3d's and OMPL's shared libraries at import time.
packages=python3,python3-venv,libgomp1,libusb-1.0-0,libgl1,libegl1

host_mirror() {
    local uri=""
    if [ -r /etc/apt/sources.list.d/debian.sources ]; then
        uri=$(awk '/^URIs:/ {print $2; exit}' /etc/apt/sources.list.d/debian.sources)
    fi
    if [ -z "$uri" ] && [ -r /etc/apt/sources.list ]; then
        uri=$(awk '$1 == "deb" && $2 !~ /^\[/ {print $2; exit}' /etc/apt/sources.list)
    fi
    echo "$uri"
}

command -v debootstrap >/dev/null || { echo "build_base_image.sh: debootstrap is not installed" >&2; exit 1; }
mirror=${DEBIAN_MIRROR:-$(host_mirror)}
work=$(mktemp -d /var/tmp/robonav-rootfs.XXXXXX)
trap 'rm -rf "$work"' EXIT

echo "debootstrap $suite ($packages) from ${mirror:-the default mirror}"
# shellcheck disable=SC2086  # an empty mirror means debootstrap's default
debootstrap --variant=minbase --include="$packages" "$suite" "$work/rootfs" $mirror >"$work/debootstrap.log" 2>&1 || {
    tail -30 "$work/debootstrap.log" >&2
    exit 1
}
# Nothing in the image installs Debian packages later: drop apt's lists and caches, docs and locales.
rm -rf "$work/rootfs"/var/lib/apt/lists/* "$work/rootfs"/var/cache/apt/* "$work/rootfs"/var/log/* \
       "$work/rootfs"/usr/share/doc/* "$work/rootfs"/usr/share/man/* "$work/rootfs"/usr/share/info/* \
       "$work/rootfs"/usr/share/locale/*
# open3d links libGL and libEGL, so they must load, but nothing here renders through OpenGL
# (pybullet's camera uses its CPU renderer): mesa's drivers and the LLVM they JIT with are
# 160 MB the image does not need.
find "$work/rootfs/usr/lib" \( -name dri -type d -o -name 'libLLVM-*.so*' -o -name 'libz3.so*' \) -prune \
    -exec rm -rf {} +
tar --numeric-owner -C "$work/rootfs" -c . |
    docker import -c 'ENV LANG=C.UTF-8' -c 'CMD ["/bin/bash"]' -m "Debian $suite minbase with Python 3" - "$tag" >/dev/null
echo "built $tag ($(docker image inspect -f '{{.Size}}' "$tag" | awk '{printf "%.0f MB", $1 / 1e6}'))"
