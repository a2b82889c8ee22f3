#!/usr/bin/env bash
# Re-pin docker/requirements.txt: resolve the project's 'services' extra in a fresh venv and
# freeze it (run on Python 3.11, linux x86_64, like the image).
set -euo pipefail
cd "$(dirname "$0")/.."
venv=$(mktemp -d)
trap 'rm -rf "$venv"' EXIT
python3 -m venv "$venv"
"$venv/bin/pip" install --quiet '.[services]'
{
    echo "# Pinned runtime requirements of the image (docker/Dockerfile): the 'services' extra of"
    echo "# pyproject.toml resolved on Python 3.11 / linux x86_64. Regenerate: docker/pin-requirements.sh"
    "$venv/bin/pip" freeze --exclude-editable --exclude psm-dataflow | sort -f
} > docker/requirements.txt
echo "pinned $(grep -c '==' docker/requirements.txt) packages"
