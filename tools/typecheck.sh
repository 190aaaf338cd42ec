#!/usr/bin/env bash
# Type-check the three packages as they install (retargetd.daemon, .protocols,
# .replay): mypy cannot follow setuptools' package-dir mapping of an editable
# install, so the folders are linked under a temporary retargetd/ namespace root.
set -euo pipefail
repo="$(cd "$(dirname "$0")/.." && pwd)"
root="$(mktemp -d)"
trap 'rm -rf "$root"' EXIT
mkdir -p "$root/retargetd"
for pkg in daemon protocols replay; do ln -s "$repo/$pkg" "$root/retargetd/$pkg"; done
cd "$root"
mypy --config-file "$repo/pyproject.toml" --namespace-packages --explicit-package-bases \
    -p retargetd.daemon -p retargetd.protocols -p retargetd.replay
