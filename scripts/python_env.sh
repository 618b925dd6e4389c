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

# Sourced by scripts/test.sh and scripts/demo.sh: sets PYTHON to the checkout's own venv,
# $WS/venv (.colcon/venv), created on first use from $PYTHON (default python3). The scripts
# never pip-install into $PYTHON itself: a Debian/Ubuntu system Python refuses (PEP 668), and
# a pyenv or conda interpreter would get a global editable install that later points at
# whichever checkout ran last. Expects REPO_ROOT, WS and the step helper.
#
# --system-site-packages keeps apt's Python modules visible (ament_copyright and
# ament_xmllint; rclpy of a ROS 2 install comes through PYTHONPATH anyway); the venv's own
# packages come first. pip keeps its download/wheel cache (~/.cache/pip), so a re-created
# venv installs from cache.
# RD_SKIP_INSTALL=1 with no venv yet: use $PYTHON as it is (offline re-runs), install nothing.
VENV="${RD_VENV:-$WS/venv}"
if [ -x "$VENV/bin/python" ] && "$VENV/bin/python" -m pip --version >/dev/null 2>&1; then
  PYTHON="$VENV/bin/python"
elif [ "${RD_SKIP_INSTALL:-0}" = 1 ]; then
  echo "no venv at $VENV and RD_SKIP_INSTALL=1: using $PYTHON as it is"
else
  step "creating the venv $VENV (from $PYTHON)"
  # A half-made venv (Debian without python3-venv has no ensurepip) is re-created.
  # python3-venv system-wide only with RD_APT=1 (scripts/system_packages.sh).
  if ! "$PYTHON" -m venv --clear --system-site-packages "$VENV"; then
    "$REPO_ROOT/scripts/system_packages.sh" python3-venv
    "$PYTHON" -m venv --clear --system-site-packages "$VENV"
  fi
  PYTHON="$VENV/bin/python"
fi
# colcon must not crawl the venv for packages.
[ ! -d "$VENV" ] || touch "$VENV/COLCON_IGNORE"
# rclpy's PyPI wheels installed in the base interpreter (seen through --system-site-packages)
# load their C libraries through LD_LIBRARY_PATH, which the wheels' bootstrap sets for the
# venv's own prefix only: add the base interpreter's (its lib/ and site-packages/ros_*.libs).
rd_base_ld="$("$PYTHON" - <<'PYEOF'
import glob
import os
import sys
import sysconfig
if sys.prefix != sys.base_prefix:
    lib = os.path.join(sys.base_prefix, 'lib')
    site = sysconfig.get_path('purelib', vars={'base': sys.base_prefix,
                                               'platbase': sys.base_prefix})
    if os.path.exists(os.path.join(lib, 'librcl.so')):
        print(os.pathsep.join([lib] + sorted(glob.glob(os.path.join(site, 'ros_*.libs')))))
PYEOF
)"
if [ -n "$rd_base_ld" ]; then
  export LD_LIBRARY_PATH="$rd_base_ld${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
fi

# rd_pip_install ARGS...: scripts/pip_install.sh (uv, or pip).
# shellcheck source=scripts/pip_install.sh
source "$REPO_ROOT/scripts/pip_install.sh"
