#!/bin/sh
# Put the zenoh filesystem storage backend (libzenoh_backend_fs.so) into DEST_DIR.
#
#   fetch-fs-backend.sh [DEST_DIR]        (default /zenoh/backends)
#
# Runs before zenohd, as an init container in the eclipse/zenoh image itself (Alpine busybox:
# sh, wget, unzip). The eclipse/zenoh image carries zenohd with the REST and storage-manager
# plugins but no filesystem backend, and a backend must be built for the same zenoh version
# and target as zenohd (no stable Rust ABI), so the version here must match the image tag.
#
# Environment:
#   ZENOH_VERSION         default 1.10.2 (the eclipse/zenoh image tag)
#   ZENOH_TARGET          default <uname -m>-unknown-linux-musl (the image is musl)
#   ZENOH_BACKEND_FS_URL  full URL of the release zip, to use a mirror or an internal copy
# Does nothing when DEST_DIR already holds the library for that version and target.
set -eu

dest="${1:-/zenoh/backends}"
version="${ZENOH_VERSION:-1.10.2}"
target="${ZENOH_TARGET:-$(uname -m)-unknown-linux-musl}"
name="zenoh-backend-filesystem-${version}-${target}-standalone.zip"
url="${ZENOH_BACKEND_FS_URL:-https://github.com/eclipse-zenoh/zenoh-backend-filesystem/releases/download/${version}/${name}}"
stamp="${version} ${target}"

mkdir -p "$dest"
if [ -f "$dest/libzenoh_backend_fs.so" ] && [ "$(cat "$dest/.fs-backend-version" 2>/dev/null)" = "$stamp" ]; then
  echo "fetch-fs-backend: $dest/libzenoh_backend_fs.so ($stamp) already present"
  exit 0
fi

work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
echo "fetch-fs-backend: downloading $url"
wget -q -O "$work/backend.zip" "$url"
unzip -q -o "$work/backend.zip" -d "$work/unpacked"
lib="$(find "$work/unpacked" -name 'libzenoh_backend_fs.so' | head -n 1)"
if [ -z "$lib" ]; then
  echo "fetch-fs-backend: libzenoh_backend_fs.so not found in $name" >&2
  exit 1
fi
cp "$lib" "$dest/libzenoh_backend_fs.so.tmp"
mv "$dest/libzenoh_backend_fs.so.tmp" "$dest/libzenoh_backend_fs.so"
echo "$stamp" >"$dest/.fs-backend-version"
echo "fetch-fs-backend: installed $dest/libzenoh_backend_fs.so ($stamp)"
