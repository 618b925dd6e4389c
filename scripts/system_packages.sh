#!/usr/bin/env bash
# Copyright 2026 reduced_dynamics developers
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

# The one place scripts/ touch the system: scripts/system_packages.sh PACKAGE...
#
# Installs the Debian packages among PACKAGE... that are not installed, system-wide, and
# only when asked (issue 24.3: scripts/test.sh changes only the checkout):
#   RD_APT unset or 0   installs nothing: names the missing packages, exit 1 (0: none missing)
#   RD_APT=1            apt-get install --no-upgrade --no-install-recommends of the missing
#                       ones; refused (exit 1) when apt would upgrade an installed package
#                       to satisfy them (the listed ones are named)
#   RD_APT=upgrade      as 1, and such upgrades are allowed (CI: a fresh, throwaway machine)
# `apt-get update` runs only when a missing package is unknown to the package lists.
# As root, or through `sudo -n`.

set -euo pipefail

RD_APT="${RD_APT:-0}"
export DEBIAN_FRONTEND=noninteractive

as_root() {
  if [ "$(id -u)" -eq 0 ]; then
    "$@"
  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    sudo -n "$@"
  else
    echo "system_packages: need root or passwordless sudo for: $*" >&2
    return 1
  fi
}

if [ "$#" -eq 0 ]; then
  exit 0
fi
if ! command -v dpkg-query >/dev/null 2>&1; then
  echo "system_packages: not a Debian/Ubuntu system; install the equivalents of: $*" >&2
  exit 1
fi
missing=()
for package in "$@"; do
  dpkg-query -W -f='${Status}' "$package" 2>/dev/null | grep -q 'install ok installed' \
    || missing+=("$package")
done
if [ "${#missing[@]}" -eq 0 ]; then
  echo "system packages present: $*"
  exit 0
fi
if [ "$RD_APT" = 0 ]; then
  echo "system packages missing (not installed: RD_APT=1 installs them): ${missing[*]}" >&2
  exit 1
fi
if [ "$RD_APT" != 1 ] && [ "$RD_APT" != upgrade ]; then
  echo "system_packages: RD_APT must be 0, 1 or upgrade, not '$RD_APT'" >&2
  exit 2
fi

for package in "${missing[@]}"; do
  if ! apt-cache show "$package" >/dev/null 2>&1; then
    as_root apt-get update -q
    break
  fi
done
install=(apt-get install -y -q --no-install-recommends --no-upgrade "${missing[@]}")
# A simulated run first: an "Inst NAME [OLD] (NEW ...)" line is an installed package that
# would be upgraded (--no-upgrade keeps only the named packages from being upgraded).
upgrades="$(apt-get -s "${install[@]:1}" | awk '/^Inst [^ ]+ \[/ {print $2}' | paste -sd' ')"
if [ -n "$upgrades" ] && [ "$RD_APT" != upgrade ]; then
  echo "system_packages: installing ${missing[*]} would upgrade the installed $upgrades;" \
       "nothing installed (RD_APT=upgrade allows it)" >&2
  exit 1
fi
echo "apt-get installing (RD_APT=$RD_APT): ${missing[*]}"
as_root "${install[@]}"
