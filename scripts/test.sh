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

# The one test command: ./scripts/test.sh [pytest args...]
#
# It changes only the checkout (.colcon/): nothing system-wide unless RD_APT says so.
#   1. linters pip cannot provide (ament_copyright, ament_xmllint and its xmllint:
#      python3-ament-copyright python3-ament-xmllint libxml2-utils), when their commands
#      are missing: downloaded with `apt-get download` and unpacked into .colcon/debs/root,
#      not installed (scripts/linter_packages.sh; test/linters.py runs them from there);
#      with RD_APT=1 installed system-wide instead (scripts/system_packages.sh: only the
#      missing ones, --no-upgrade, never upgrading an installed package),
#   2. creates the checkout's own venv (.colcon/venv, scripts/python_env.sh) and installs
#      the package there with uv (or pip: RD_INSTALLER) (editable, [test], [docs], [fleet]
#      and [lint] extras: [lint] =
#      ament_flake8 and ament_pep257 with the flake8/pydocstyle they run; [ros] = the real
#      rclpy wheels when no ROS 2 install provides rclpy) and colcon; checks that real rclpy
#      imports and initialises,
#   3. colcon build  (workspace under .colcon/, never build/ install/ log/),
#   4. checks the ros2-run executable lib/reduced_dynamics/reduced_dynamics_node and the
#      `reduced-dynamics` command on PATH after sourcing install/setup.bash; runs README's
#      two install blocks from clean clones (scripts/check_readme_install.sh) and
#      scripts/demo.sh (README's other command),
#   5. colcon test   (pytest runs once, its tests spread over RD_TEST_WORKERS processes by
#      pytest-xdist; its output and summary line are printed),
#   6. colcon test-result --verbose.
#
# Extra arguments go to pytest, e.g. ./scripts/test.sh -k momentum -x
#
# Environment knobs:
#   PYTHON=python3            interpreter the venv is created from
#   RD_VENV=.colcon/venv      the venv used for pip, colcon and pytest
#   RD_APT=0                  0: unpack step 1's packages into .colcon/debs; 1: apt-get
#                             install the missing system packages of step 1 (and
#                             python3-venv if the venv cannot be made); upgrade: also when
#                             that upgrades installed packages (.ci/run: a fresh machine)
#   RD_SKIP_INSTALL=1         skip the apt/pip steps (offline re-runs)
#   RD_INSTALLER=uv           step 2's installer: uv (from PyPI, ~7x faster here), or pip
#   RD_SYMLINK_INSTALL=0      plain `colcon build` instead of --symlink-install
#   RD_README_INSTALL=0       skip running README's install blocks (step 4c)
#   RD_DEMO=0                 skip running scripts/demo.sh (step 4d)
#   RD_NUMBA_OPT=             LLVM optimisation level of the kernels the demo and the
#                             tests compile (NUMBA_OPT; .ci/run: 1, ~30 % faster to
#                             compile, same outputs); unset: numba's default, 3
#   RD_TEST_WORKERS=logical   pytest-xdist workers of step 5 (logical: one per CPU; 0: one
#                             process, no xdist); each worker has a ROS domain of its own
#
# PYTHONDONTWRITEBYTECODE is unset for every step: Python then keeps the bytecode of the
# modules it compiles (__pycache__ in .colcon/venv and the checkout, both gitignored). With
# it set (as on this project's CI machine) and uv installing without bytecode, each of the
# suite's process starts compiled ~1 100 modules from source again: measured, a node's
# imports took 3.0-3.9 s of CPU without the caches, 0.8-1.0 s with them (docs/testing.md).

set -euo pipefail
unset PYTHONDONTWRITEBYTECODE

cd "$(dirname "${BASH_SOURCE[0]}")/.."
REPO_ROOT="$PWD"
WS="$REPO_ROOT/.colcon"
PKG=reduced_dynamics

PYTHON="${PYTHON:-python3}"
ORIG_PYTHON="$PYTHON"
RD_SKIP_INSTALL="${RD_SKIP_INSTALL:-0}"
RD_SYMLINK_INSTALL="${RD_SYMLINK_INSTALL:-1}"

export PIP_DISABLE_PIP_VERSION_CHECK=1
export PIP_NO_INPUT=1
export DEBIAN_FRONTEND=noninteractive
# Keep colcon away from per-user defaults/mixins (~/.colcon) so runs are reproducible.
export COLCON_HOME="$WS/home"
# Disable colcon's desktop notifications (no display in CI).
export COLCON_EXTENSION_BLOCKLIST="colcon_core.event_handler.desktop_notification${COLCON_EXTENSION_BLOCKLIST:+:$COLCON_EXTENSION_BLOCKLIST}"

step() { printf '\n==> %s   [%d s]\n' "$*" "$SECONDS"; }
warn() { printf 'WARNING: %s\n' "$*" >&2; }

# ------------------------------------------------------- 1. system packages (RD_APT)
# ament_copyright, ament_xmllint and xmllint are not on PyPI as Jazzy or Debian ship them:
# scripts/linter_packages.sh unpacks the missing Debian packages into .colcon/debs/root
# (apt-get download, not installed), or with RD_APT=1 installs them system-wide.
if [ "$RD_SKIP_INSTALL" != 1 ]; then
  step "linters pip cannot provide (RD_APT=${RD_APT:-0})"
  "$REPO_ROOT/scripts/linter_packages.sh" "$WS/debs" \
    || warn "test_copyright / test_xmllint will fail without ament_copyright, ament_xmllint," \
            "xmllint (RD_APT=1 ./scripts/test.sh installs the missing ones, or source ROS 2)"
fi

# ------------------------------------------------------ 2. python environment
# shellcheck source=scripts/python_env.sh
source "$REPO_ROOT/scripts/python_env.sh"
echo "python: $("$PYTHON" -c 'import sys; print(sys.executable, sys.version.split()[0])')"

if [ "$RD_SKIP_INSTALL" != 1 ]; then
  # Real ROS 2 Jazzy rclpy: a sourced ROS 2 install provides it; otherwise the PyPI wheels
  # of the [ros] extra (rclpy with Fast DDS and the message packages). [docs]: Sphinx, which
  # test/test_docs.py runs on docs/. [fleet]: Ray and Dask for replay-many's backends
  # (test_fleet.py; ~1 min and ~280 MB from PyPI, measured). [lint]: ament_flake8 and
  # ament_pep257 (test_flake8.py, test_pep257.py) into the venv's bin/.
  extras=test,docs,fleet,lint
  if ! "$PYTHON" -c 'import rclpy' 2>/dev/null; then
    extras=test,docs,ros,fleet,lint
  fi
  step "pip install -e '.[$extras]' colcon-common-extensions (by ${RD_INSTALLER:-uv})"
  rd_pip_install -e "$REPO_ROOT[$extras]" colcon-common-extensions
fi

# The node tests run on real rclpy: refuse to go on without it (no test double).
step "real rclpy"
"$PYTHON" - <<'EOF'
import rclpy
from rclpy.utilities import get_rmw_implementation_identifier
import rclpy.lifecycle  # noqa: F401
import diagnostic_msgs.msg, geometry_msgs.msg, lifecycle_msgs.msg  # noqa: E401,F401
import nav_msgs.msg, sensor_msgs.msg, std_msgs.msg, trajectory_msgs.msg  # noqa: E401,F401
rclpy.init()
try:
    print(f'rclpy from {rclpy.__file__}, rmw {get_rmw_implementation_identifier()}')
finally:
    rclpy.shutdown()
EOF

# Run colcon with exactly this interpreter (colcon test runs `sys.executable -m pytest`).
colcon() {
  "$PYTHON" -c 'import sys; from colcon_core.command import main; sys.exit(main())' "$@"
}

# ------------------------------------------------------------ 3. colcon build
WS_ARGS=(--base-paths "$REPO_ROOT" --build-base "$WS/build" --install-base "$WS/install")
BUILD_ARGS=()
if [ "$RD_SYMLINK_INSTALL" = 1 ]; then
  BUILD_ARGS+=(--symlink-install)
fi
step "colcon build ${BUILD_ARGS[*]}"
colcon --log-base "$WS/log" build "${WS_ARGS[@]}" "${BUILD_ARGS[@]}" \
  --packages-select "$PKG" --event-handlers console_cohesion+

# --------------------------------------------------- 4. ros2 run executable
NODE_EXE="$WS/install/$PKG/lib/$PKG/reduced_dynamics_node"
if [ ! -x "$NODE_EXE" ]; then
  echo "ERROR: missing executable $NODE_EXE (check setup.cfg [install]/[develop])" >&2
  exit 1
fi
echo "ros2 run executable: ${NODE_EXE#"$REPO_ROOT"/}"

# ------------------------------------------- 4b. colcon install: the plain command
# After `source install/setup.bash` the CLI is on PATH (bin/ wrapper, colcon's PATH hook).
step "reduced-dynamics on PATH after sourcing the colcon install"
(set +u; source "$WS/install/setup.bash"; test "$(command -v reduced-dynamics)" = \
  "$WS/install/$PKG/bin/reduced-dynamics" && reduced-dynamics --help >/dev/null) || {
  echo "ERROR: reduced-dynamics is not install/$PKG/bin/reduced-dynamics after sourcing" >&2
  exit 1
}
echo "$(set +u; source "$WS/install/setup.bash"; command -v reduced-dynamics)"

# ------------------------------------------ 4c. README's install paths (clean clones)
# README's "The ROS 2 path" blocks, run as written (scripts/check_readme_install.sh);
# needs the network or a warm pip cache, so RD_SKIP_INSTALL=1 skips it.
# It runs in the background during colcon test (mostly pip installing: another core);
# its log is printed, and its failure fails the run, at the end.
readme_pid=
trap '[ -z "$readme_pid" ] || kill "$readme_pid" 2>/dev/null || true' EXIT
if [ "$RD_SKIP_INSTALL" != 1 ] && [ "${RD_README_INSTALL:-1}" = 1 ]; then
  step "README install paths (background, log .colcon/readme_install.log)"
  PYTHON="$ORIG_PYTHON" "$REPO_ROOT/scripts/check_readme_install.sh" \
    > "$WS/readme_install.log" 2>&1 &
  readme_pid=$!
fi

# ---------------------------------------------- 4d'. the compiled kernels of this run
# The demo compiles the filter kernels (~4 min of CPU on an empty cache) and the tests load
# them. RD_NUMBA_OPT=1 (.ci/run sets it: its machine is thrown away) compiles them at LLVM's
# optimisation level 1 instead of numba's 3: ~30 % less CPU (151 s against 214 s for
# warm_up's kernels), golden outputs bit-identical, the kernels' speed within this machine's
# noise (docs/parallel_tests.md, "Stop 30"). Unset elsewhere: numba caches beside the
# modules without the level in its key, so a developer's later runs would load these.
# Set after README's install check started: that one runs as a user's would.
if [ -n "${RD_NUMBA_OPT:-}" ]; then
  export NUMBA_OPT="$RD_NUMBA_OPT"
fi

# ---------------------------------------------- 4d. README's other command: demo.sh
# Same venv (scripts/python_env.sh), outputs under .colcon/demo; about 20 s.
if [ "${RD_DEMO:-1}" = 1 ]; then
  step "scripts/demo.sh"
  PYTHON="$ORIG_PYTHON" "$REPO_ROOT/scripts/demo.sh" "$WS/demo"
fi

# ------------------------------------------------------------- 5. colcon test
# Every pytest argument is prefixed by a space so colcon's argparse never mistakes
# it for one of its own options (colcon strips the space again).
# pytest-xdist (the [test] extra): the tests in parallel worker processes, each with a ROS
# domain of its own (conftest.py); tests marked xdist_group share one worker (loadgroup).
RD_TEST_WORKERS="${RD_TEST_WORKERS:-logical}"
pytest_args=()
if [ "$RD_TEST_WORKERS" != 0 ]; then
  if "$PYTHON" -c 'import xdist' 2>/dev/null; then
    pytest_args+=(-n "$RD_TEST_WORKERS" --dist loadgroup)
  else
    warn "pytest-xdist is not installed: the tests run in one process"
  fi
fi
pytest_args+=("$@")
PYTEST_ARGS=()
if [ "${#pytest_args[@]}" -gt 0 ]; then
  PYTEST_ARGS+=(--pytest-args)
  for a in "${pytest_args[@]}"; do
    PYTEST_ARGS+=(" $a")
  done
fi
step "colcon test"
rc=0
colcon --log-base "$WS/log" test "${WS_ARGS[@]}" --test-result-base "$WS/test_results" \
  --packages-select "$PKG" --return-code-on-test-failure \
  --event-handlers console_direct+ "${PYTEST_ARGS[@]}" || rc=$?

# ------------------------------------------------------ 6. colcon test-result
step "colcon test-result"
colcon --log-base "$WS/log" test-result --test-result-base "$WS/test_results" --verbose \
  || { [ "$rc" -ne 0 ] || rc=1; }

if [ -n "$readme_pid" ]; then
  step "README install paths (waiting for the background run)"
  readme_rc=0
  wait "$readme_pid" || readme_rc=$?
  readme_pid=
  if [ "$readme_rc" -eq 0 ]; then
    grep -E '^(==> README way|README way|no /opt/ros)' "$WS/readme_install.log" || true
  else
    cat "$WS/readme_install.log"
    echo "ERROR: README's install paths failed (log above)" >&2
    rc=1
  fi
fi

exit "$rc"
