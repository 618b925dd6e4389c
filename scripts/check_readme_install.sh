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

# Runs README's install blocks ("The ROS 2 path", the ```bash blocks after the markers
# <!-- readme-ci: ros-apt --> and <!-- readme-ci: ros-wheels -->) as written, each with
# `bash -e` in a fresh clone of this checkout's HEAD (committed work only) and a throwaway
# HOME, then checks what the block promises (the command on PATH is the one just built).
#
# Way A needs /opt/ros/jazzy/setup.bash. Where there is none (CI: plain Debian 12), a
# stand-in does what that file does for Python: a prefix holding the same rclpy, message
# packages and colcon (the Jazzy PyPI wheels, in their own venv) exported through PYTHONPATH
# and LD_LIBRARY_PATH; that path is the one substitution made in the block.
# pip keeps using the real download cache (PIP_CACHE_DIR), so the runs stay fast; the
# stand-in itself is installed by uv (scripts/pip_install.sh), as the checkout's venv is.
# Usage: scripts/check_readme_install.sh [apt|wheels ...]   (default both)

set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
REPO_ROOT="$PWD"
README="$REPO_ROOT/README.md"
PYTHON="${PYTHON:-python3}"
export PIP_CACHE_DIR="${PIP_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/pip}"
export PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1
# A domain of its own: the smoke runs must not talk to other nodes on this machine.
export ROS_DOMAIN_ID="${RD_README_DOMAIN_ID:-87}"

WHICH=("$@")
[ "${#WHICH[@]}" -gt 0 ] || WHICH=(apt wheels)

# shellcheck source=scripts/pip_install.sh
source "$REPO_ROOT/scripts/pip_install.sh"

TMP="$(mktemp -d "${TMPDIR:-/tmp}/rd-readme.XXXXXX")"
trap 'rm -rf "$TMP"' EXIT

# The first ```bash block after the marker line, verbatim.
readme_block() {
  awk -v marker="<!-- readme-ci: $1 -->" '
    $0 == marker { found = 1; next }
    found && !inblock && /^```bash$/ { inblock = 1; next }
    inblock && /^```$/ { exit }
    inblock { print }
  ' "$README"
}

# A stand-in for /opt/ros/jazzy/setup.bash (see the header).
fake_ros() {
  local prefix="$TMP/opt_ros_jazzy"
  "$PYTHON" -m venv "$prefix/venv"
  # The stand-in is this script's scaffolding, not a README step: installed by uv (pip when
  # uv is not available), 6 s of CPU against pip's 23 s here, the same 152 distributions.
  PYTHON="$prefix/venv/bin/python" rd_pip_install "ros-jazzy-rclpy[fastrtps]" \
    ros-jazzy-common-interfaces colcon-common-extensions >&2
  local site shadow entry
  site="$("$prefix/venv/bin/python" -c 'import sysconfig; print(sysconfig.get_path("purelib"))')"
  # What /opt/ros/jazzy's site-packages holds: the ROS packages (and colcon, as apt's
  # python3-colcon-* in the system's), not the venv's own pip/setuptools, which on a
  # Debian python would displace the interpreter's own build tools.
  shadow="$prefix/lib/python3/site-packages"
  mkdir -p "$shadow"
  for entry in "$site"/*; do
    case "${entry##*/}" in
      pip | pip-* | setuptools | setuptools-* | pkg_resources | _distutils_hack | \
        distutils-precedence.pth | wheel | wheel-* | uv | uv-* | __pycache__) ;;
      *) ln -s "$entry" "$shadow/" ;;
    esac
  done
  cat > "$prefix/setup.bash" <<EOF
# stand-in for /opt/ros/jazzy/setup.bash (scripts/check_readme_install.sh): what the
# wheels' bootstrap would set (their libraries: the prefix's lib/ and site-packages/*.libs)
export PYTHONPATH="$shadow\${PYTHONPATH:+:\$PYTHONPATH}"
export LD_LIBRARY_PATH="$prefix/venv/lib:$(find "$site" -maxdepth 1 -name '*.libs' -type d | paste -sd:)\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}"
export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1  # LD_LIBRARY_PATH is set: no re-exec needed
export ROS_DISTRO=jazzy ROS_VERSION=2 ROS_PYTHON_VERSION=3
EOF
  echo "$prefix/setup.bash"
}

run_block() {
  local name="$1" checks="$2" block script clone home start
  block="$(readme_block "ros-$name")"
  if [ -z "$block" ]; then
    echo "ERROR: README has no \`\`\`bash block after <!-- readme-ci: ros-$name -->" >&2
    return 1
  fi
  clone="$TMP/$name/reduced_dynamics"
  home="$TMP/$name/home"
  mkdir -p "$home"
  git clone -q "$REPO_ROOT" "$clone"
  if [ "$name" = apt ] && [ ! -f /opt/ros/jazzy/setup.bash ]; then
    local stand_in
    echo "no /opt/ros/jazzy: a stand-in from the Jazzy wheels"
    stand_in="$(fake_ros)"
    block="${block//\/opt\/ros\/jazzy\/setup.bash/$stand_in}"
  fi
  script="$TMP/$name.sh"
  printf 'set -e -o pipefail\n%s\n%s\n' "$block" "$checks" > "$script"
  printf '\n==> README way %s, from a clean clone (%s):\n%s\n' "$name" "$clone" "$block"
  start=$SECONDS
  (cd "$clone" && HOME="$home" bash "$script")
  echo "README way $name: OK in $((SECONDS - start)) s"
}

for way in "${WHICH[@]}"; do
  case "$way" in
    apt)
      run_block apt '
test "$(command -v reduced-dynamics)" = "$HOME/ws/install/reduced_dynamics/bin/reduced-dynamics"
for exe in reduced-dynamics reduced_dynamics_node; do   # what ros2 run finds
  test -x "$HOME/ws/install/reduced_dynamics/lib/reduced_dynamics/$exe"
done
head -1 "$HOME/ws/install/reduced_dynamics/lib/reduced_dynamics/reduced_dynamics_node" \
  | grep -qx "#!$HOME/ws/venv/bin/python"
"$HOME/ws/venv/bin/python" -c "import rclpy, reduced_dynamics.node"' ;;
    wheels)
      run_block wheels '
test "$(command -v reduced_dynamics_node)" = "$HOME/rd-venv/bin/reduced_dynamics_node"
test "$(command -v reduced-dynamics)" = "$HOME/rd-venv/bin/reduced-dynamics"' ;;
    *) echo "unknown way $way (apt, wheels)" >&2; exit 2 ;;
  esac
done
