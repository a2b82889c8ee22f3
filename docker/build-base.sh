#!/usr/bin/env bash
# Build a local stand-in for the public Python 3.11 slim image, for machines that cannot pull
# from a registry: a Debian rootfs with python3, venv and libgomp1 (debootstrap), imported as
# an image. The Debian mirror is the host's (its apt sources); the host's CA bundle goes into
# the image so that pip inside it trusts the same package index as the host.
#
#   docker/build-base.sh [IMAGE]            # default IMAGE: psm-base:bookworm
#   docker build --build-arg BASE_IMAGE=psm-base:bookworm -f docker/Dockerfile .
#
# Needs root, debootstrap and a running Docker engine. Does nothing if IMAGE exists.
set -euo pipefail
image=${1:-psm-base:bookworm}
if docker image inspect "$image" >/dev/null 2>&1; then
    echo "build-base: $image exists"
    exit 0
fi
suite=bookworm
mirror=""
if [ -f /etc/apt/sources.list.d/debian.sources ]; then
    mirror=$(awk '/^URIs:/ {print $2; exit}' /etc/apt/sources.list.d/debian.sources)
fi
if [ -z "$mirror" ] && [ -f /etc/apt/sources.list ]; then
    mirror=$(awk '$1 == "deb" && $2 !~ /^\[/ {print $2; exit} $1 == "deb" {print $3; exit}' /etc/apt/sources.list)
fi
[ -n "$mirror" ] || { echo "build-base: no Debian mirror in the apt sources" >&2; exit 2; }
root=$(mktemp -d /var/tmp/psm-base.XXXXXX)
trap 'rm -rf "$root"' EXIT
echo "build-base: debootstrap $suite into $root"
debootstrap --variant=minbase \
    --include=python3,python3-venv,libgomp1,ca-certificates \
    "$suite" "$root" "$mirror" >"$root.log" 2>&1 || { tail -20 "$root.log" >&2; exit 1; }
rm -f "$root.log"
if [ -f /etc/ssl/certs/ca-certificates.crt ]; then
    cp /etc/ssl/certs/ca-certificates.crt "$root/etc/ssl/certs/ca-certificates.crt"
fi
chroot "$root" apt-get clean
rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/*.bin
# The public image has python3 on PATH as `python3` too; pip is used from a venv either way.
tar -C "$root" -c . | docker import \
    --change 'ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt' \
    --change 'ENV LANG=C.UTF-8' \
    --change 'CMD ["python3"]' - "$image" >/dev/null
echo "build-base: $image built"
