#!/usr/bin/env bash
# Debian packages the project needs; installs only what is missing (with sudo when not root).
set -euo pipefail
REQUIRED=(libosmesa6 libgl1 libegl1 libegl-mesa0 libportaudio2 espeak-ng libespeak-ng1 libsndfile1)
OPTIONAL=(chromium)  # the dashboard's browser tests; skipped with a reason when absent
# npm installs three.js for the page's avatar (package.json); Debian's only where no Node.js is installed already
command -v npm >/dev/null 2>&1 || OPTIONAL+=(nodejs npm)

missing() { for p in "$@"; do dpkg -s "$p" >/dev/null 2>&1 || echo "$p"; done; }
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
need=$(missing "${REQUIRED[@]}" "${OPTIONAL[@]}")
[ -z "$need" ] && exit 0
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
# shellcheck disable=SC2046
$SUDO apt-get install -y -qq --no-install-recommends $(missing "${REQUIRED[@]}") >/dev/null
opt=$(missing "${OPTIONAL[@]}")
if [ -n "$opt" ]; then
  # shellcheck disable=SC2086
  $SUDO apt-get install -y -qq --no-install-recommends $opt >/dev/null || echo "note: could not install $opt (optional)"
fi
