#!/usr/bin/env bash
# Build the robonav image from a wheelhouse made on the host: nothing is downloaded in the build.
#
#   docker/build.sh [IMAGE]          (default IMAGE: robonav-arm:latest)
#
# 1. Base image: BASE_IMAGE (default python:3.11-slim) if present or pullable, else a Debian
#    bookworm base built locally by docker/build_base_image.sh (no registry needed).
# 2. Wheelhouse on the host: every dependency and robonav-arm itself as wheels, in
#    build/docker/{deps,app} (pip wheel; PyPI or a local index/--find-links the host's pip uses).
# 3. docker build from that wheelhouse, with --network none when the base has the shared
#    libraries the wheels need (the local base does; the public slim image does not).
# Prints the image size. PYTHON (default .venv/bin/python, else python3) must be Python 3.11,
# the base image's Python.
set -euo pipefail
cd "$(dirname "$0")/.."

image=${1:-robonav-arm:latest}
base=${BASE_IMAGE:-python:3.11-slim}
local_base=${LOCAL_BASE_IMAGE:-robonav-base:bookworm}
python=${PYTHON:-$( [ -x .venv/bin/python ] && echo .venv/bin/python || echo python3 )}
ctx=build/docker

if ! docker image inspect "$base" >/dev/null 2>&1 && ! docker pull -q "$base" >/dev/null 2>&1; then
    echo "base image $base cannot be pulled: using $local_base"
    base=$local_base
    docker image inspect "$base" >/dev/null 2>&1 || docker/build_base_image.sh "$base"
fi

"$python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' || {
    echo "build.sh: $python is not Python 3.11; the wheels must match the image's Python 3.11" >&2; exit 1; }
mkdir -p "$ctx/deps" "$ctx/app"
fresh=$(mktemp -d "$ctx/.wheels.XXXXXX")
trap 'rm -rf "$fresh"' EXIT
"$python" -m pip wheel -q --disable-pip-version-check --find-links "$ctx/deps" --wheel-dir "$fresh" . 2> >(grep -v "^WARNING: Location" >&2)
rm -f "$ctx/app/"*.whl
mv "$fresh"/robonav_arm-*.whl "$ctx/app/"
# Replace the dependency wheels only when the set changed, so docker reuses their layer.
if [ "$(cd "$fresh" && ls | sort)" != "$(cd "$ctx/deps" && ls | sort)" ]; then
    rm -rf "$ctx/deps" && mv "$fresh" "$ctx/deps" && mkdir -p "$fresh"
fi

# The build installs only from the wheelhouse. A base that lacks the shared libraries the
# wheels load (the public slim image) gets them from Debian in the build, which needs network;
# with a base that has them (the local one) the build runs with no network at all.
network=(--network none)
if ! docker run --rm --network none --entrypoint dpkg "$base" -s libgomp1 libusb-1.0-0 libgl1 libegl1 >/dev/null 2>&1; then
    echo "base $base lacks libgomp1/libusb-1.0-0/libgl1/libegl1: the build installs them with network"
    network=()
fi
docker build "${network[@]}" --build-arg BASE_IMAGE="$base" -f docker/Dockerfile -t "$image" "$ctx"
echo "image $image: $(docker image inspect -f '{{.Size}}' "$image" | awk '{printf "%.0f MB", $1 / 1e6}') (base $base)"
