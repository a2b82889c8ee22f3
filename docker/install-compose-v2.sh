#!/usr/bin/env bash
# Installs Docker Compose v2 (the `docker compose` CLI plugin) on Debian 12, next to the
# docker-compose 1.29 that Debian 12 ships, so that both can be used and tested.
#
# Debian 12 has no Compose v2 package; Debian 13 ("trixie") has it, as the statically linked
# `docker-compose` 2.x package (it needs only libc6 >= 2.34, which Debian 12 has). This script
# downloads that package with apt from the Debian mirror this machine's apt sources already use
# (apt checks the archive's signature against Debian's keyring), through a private apt state
# directory, so the system's package lists and sources are left unchanged, and installs only
# the plugin binary to /usr/libexec/docker/cli-plugins/docker-compose. /usr/bin/docker-compose
# (1.29) is not touched.
#
# Usage: bash docker/install-compose-v2.sh   (as root; does nothing when `docker compose` works)
set -euo pipefail

PLUGIN_DIR=/usr/libexec/docker/cli-plugins
SUITE=trixie
KEYRING=/usr/share/keyrings/debian-archive-keyring.gpg

if docker compose version >/dev/null 2>&1; then
    docker compose version
    exit 0
fi

# The mirror of the system's Debian "main" source: deb822 (*.sources) or one-line format.
mirror=""
for f in /etc/apt/sources.list.d/*.sources; do
    [ -f "$f" ] || continue
    mirror=$(awk '/^URIs:/ {print $2; exit}' "$f")
    [ -n "$mirror" ] && break
done
if [ -z "$mirror" ]; then
    mirror=$(grep -hE '^deb ' /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null \
        | grep -v security | sed -E 's/^deb (\[[^]]*\] )?//' | awk '{print $1; exit}')
fi
if [ -z "$mirror" ]; then
    echo "install-compose-v2: no Debian source found in /etc/apt" >&2
    exit 1
fi
mirror=${mirror%/}
case "$mirror" in
    */debian) ;;
    *) echo "install-compose-v2: $mirror is not a Debian archive" >&2; exit 1 ;;
esac

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
chmod 755 "$work"
mkdir -p "$work/lists/partial" "$work/cache/archives/partial"
echo "deb [signed-by=$KEYRING] $mirror $SUITE main" >"$work/sources.list"
apt_opts=(-o "Dir::Etc::SourceList=$work/sources.list" -o "Dir::Etc::SourceParts=$work/none"
          -o "Dir::State::Lists=$work/lists" -o "Dir::Cache=$work/cache"
          -o "APT::Sandbox::User=root" -qq)
apt-get "${apt_opts[@]}" update
version=$(apt-cache "${apt_opts[@]}" policy docker-compose | awk '/Candidate:/ {print $2}')
case "$version" in
    2.*) ;;
    *) echo "install-compose-v2: $SUITE offers docker-compose '$version', not 2.x" >&2; exit 1 ;;
esac
(cd "$work" && apt-get "${apt_opts[@]}" download "docker-compose=$version")
dpkg-deb -x "$work"/docker-compose_*.deb "$work/root"
install -D -m 0755 "$work/root$PLUGIN_DIR/docker-compose" "$PLUGIN_DIR/docker-compose"
docker compose version
