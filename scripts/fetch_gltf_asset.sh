#!/usr/bin/env bash
# Fetch the third-party glTF asset of tests/test_gltf.py from Debian's archive:
# the Khronos sample model ClearCoatTest (glTF 2.0, exported by Blender, with
# RibsNormal.png and PlasticWrap_normals.jpg normal maps and no TANGENT), as
# shipped in the package assimp-testmodels. Only its folder and the package's
# copyright file are kept, in tests/data/thirdparty/ (ignored by git), with a
# SOURCE.txt that records the .deb's version and SHA256.
# Usage: scripts/fetch_gltf_asset.sh   (idempotent; exits 1 if it cannot fetch)
set -euo pipefail
cd "$(dirname "$0")/.."
PACKAGE=assimp-testmodels
VERSION=5.2.5~ds0-1            # Debian 12 (bookworm); any other version is taken if it is gone
MODEL=usr/share/assimp/models/glTF2/ClearCoat-glTF
DEST=tests/data/thirdparty/$PACKAGE
if [ -f "$DEST/ClearCoat-glTF/ClearCoatTest.gltf" ] && [ -f "$DEST/SOURCE.txt" ]; then
    exit 0
fi
if ! command -v apt-get >/dev/null 2>&1 || ! command -v dpkg-deb >/dev/null 2>&1; then
    echo "setup: no apt-get/dpkg-deb; cannot fetch $PACKAGE (the third-party glTF tests skip)"
    exit 1
fi
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT

# The pinned version, else whatever the archive has; refresh the lists once if both fail.
download() {
    (cd "$tmp" && { apt-get download -qq "$PACKAGE=$VERSION" || apt-get download -qq "$PACKAGE"; }) \
        >/dev/null 2>&1
}
if ! download; then
    [ "$(id -u)" = 0 ] && apt-get update -qq >/dev/null 2>&1 || true
    if ! download; then
        echo "setup: apt-get download $PACKAGE failed (the third-party glTF tests skip)"
        exit 1
    fi
fi
deb=$(ls "$tmp"/"$PACKAGE"_*.deb)
dpkg-deb -x "$deb" "$tmp/x"
if [ ! -f "$tmp/x/$MODEL/ClearCoatTest.gltf" ]; then
    echo "setup: $(basename "$deb") has no $MODEL/ClearCoatTest.gltf (the third-party glTF tests skip)"
    exit 1
fi

# Copy the asset and its licence; write down where it came from.
rm -rf "$DEST"
mkdir -p "$DEST"
cp -r "$tmp/x/$MODEL" "$DEST/"
cp "$tmp/x/usr/share/doc/$PACKAGE/copyright" "$DEST/copyright"
cat >"$DEST/SOURCE.txt" <<EOF
ClearCoat-glTF/: the Khronos glTF sample model ClearCoatTest ("Copyright 2020 Analytical
Graphics, Inc. CC-BY 4.0. Model and textures by Ed Mackey", KhronosGroup/glTF-Sample-Models,
2.0/ClearCoatTest/README.md), taken unmodified from Debian's package
$(dpkg-deb -f "$deb" Package) $(dpkg-deb -f "$deb" Version) ($(basename "$deb"),
SHA256 $(sha256sum "$deb" | cut -d' ' -f1)),
path /$MODEL.
Debian's licence statement for the package is ./copyright (test models: BSD-3-clause
unless listed otherwise). Fetched by scripts/fetch_gltf_asset.sh for tests/test_gltf.py.
EOF
echo "setup: fetched ClearCoatTest.gltf from $(basename "$deb") into $DEST"
