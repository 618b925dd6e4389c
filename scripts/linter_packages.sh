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

# The ament linters pip cannot provide: scripts/linter_packages.sh DIR
#
# ament_copyright, ament_xmllint and its xmllint (Debian packages python3-ament-copyright,
# python3-ament-xmllint, libxml2-utils) are not on PyPI as Jazzy or Debian ship them (PyPI's
# ament-xmllint fetches package.xml's schema from the network; Debian's has it locally).
# Present already (on PATH: the Debian packages or a sourced ROS 2): nothing to do. Otherwise
#   RD_APT unset or 0   the missing packages (and python3-ament-lint, which both import) are
#                       downloaded with `apt-get download` into DIR and unpacked with
#                       `dpkg -x` into DIR/root, NOT installed: nothing outside DIR changes.
#                       test/linters.py runs them from there (DIR/root/usr/bin on PATH,
#                       DIR/root/usr/lib/python3/dist-packages on PYTHONPATH, DIR/catalog.xml
#                       as XML_CATALOG_FILES so xmllint reads package.xml's schema from
#                       DIR/root/usr/share/ament_xmllint instead of the network).
#                       Without apt or its package lists: one line naming RD_APT=1, exit 1.
#   RD_APT=1 / upgrade  scripts/system_packages.sh installs the missing ones system-wide.

set -euo pipefail

if [ "$#" -ne 1 ]; then
  echo "usage: scripts/linter_packages.sh DIR" >&2
  exit 2
fi
DIR="$1"
ROOT="$DIR/root"
RD_APT="${RD_APT:-0}"
LINTERS=(ament_copyright:python3-ament-copyright ament_xmllint:python3-ament-xmllint
         xmllint:libxml2-utils)

wanted=()
for entry in "${LINTERS[@]}"; do
  name="${entry%%:*}"
  if command -v "$name" >/dev/null 2>&1; then
    continue
  fi
  # An earlier unpacked copy counts only when no system install was asked for.
  if [ "$RD_APT" = 0 ] && [ -x "$ROOT/usr/bin/$name" ]; then
    continue
  fi
  wanted+=("${entry#*:}")
done
if [ "${#wanted[@]}" -eq 0 ]; then
  echo "ament_copyright, ament_xmllint, xmllint: present" \
       "($(command -v ament_copyright || echo "$ROOT/usr/bin/ament_copyright"))"
  exit 0
fi
if [ "$RD_APT" != 0 ]; then
  exec "$(dirname "${BASH_SOURCE[0]}")/system_packages.sh" "${wanted[@]}"
fi

packages=("${wanted[@]}")
case " ${wanted[*]} " in
  *" python3-ament-"*) packages+=(python3-ament-lint) ;;
esac
mkdir -p "$DIR"
rm -f "$DIR"/*.deb
# apt-get download needs no root, only apt's package lists (/var/lib/apt/lists).
if ! command -v apt-get >/dev/null 2>&1 \
    || ! (cd "$DIR" && apt-get download "${packages[@]}") > "$DIR/download.log" 2>&1; then
  echo "linter_packages: could not apt-get download ${packages[*]} (no apt or no package" \
       "lists, $DIR/download.log); RD_APT=1 ./scripts/test.sh installs them, or source ROS 2" >&2
  exit 1
fi
for package in "${packages[@]}"; do
  dpkg -x "$(ls "$DIR/${package}"_*.deb)" "$ROOT"
done
# Debian's ament_xmllint looks for the schema only under /usr/share/ament_xmllint; this
# catalog sends xmllint to the unpacked copy instead of download.ros.org.
schemas="$ROOT/usr/share/ament_xmllint/xml-catalog/download.ros.org/schema/"
cat > "$DIR/catalog.xml" <<CATALOG
<?xml version="1.0"?>
<catalog xmlns="urn:oasis:names:tc:entity:xmlns:xml:catalog">
  <rewriteURI uriStartString="http://download.ros.org/schema/" rewritePrefix="file://$schemas"/>
  <rewriteSystem systemIdStartString="http://download.ros.org/schema/"
                 rewritePrefix="file://$schemas"/>
</catalog>
CATALOG
echo "unpacked into $ROOT (not installed): ${packages[*]}"
if [ -x "$ROOT/usr/bin/xmllint" ] && ! "$ROOT/usr/bin/xmllint" --version >/dev/null 2>&1; then
  echo "linter_packages: the unpacked xmllint does not run with this system's libxml2" \
       "($ROOT/usr/bin/xmllint --version); RD_APT=1 ./scripts/test.sh installs it" >&2
  exit 1
fi
