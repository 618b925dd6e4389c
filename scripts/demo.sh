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

# The main job on the embedded default robot (the paper's spacecraft, section 6):
#   1. installs the package (pip, editable) into the checkout's venv .colcon/venv if it is
#      not importable there yet,
#   2. simulates a 10 s bag with full dynamics: held joint torques and a thruster pulse,
#   3. replays it through the estimator into an output bag, prints the summary,
#   4. writes plots of momentum, drift, shape state and prediction residual.
# Usage: ./scripts/demo.sh [OUT_DIR]   (default out/demo)

set -euo pipefail
# Python keeps the bytecode it compiles (.colcon/venv, the checkout) even where
# PYTHONDONTWRITEBYTECODE is set: the four commands below are four processes (docs/testing.md).
unset PYTHONDONTWRITEBYTECODE
cd "$(dirname "${BASH_SOURCE[0]}")/.."
REPO_ROOT="$PWD"
WS="$REPO_ROOT/.colcon"
PYTHON="${PYTHON:-python3}"
OUT="${1:-out/demo}"
export PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1

step() { printf '\n==> %s\n' "$*"; }
# The checkout's own venv, .colcon/venv (scripts/python_env.sh): never the interpreter itself.
RD_SKIP_INSTALL=0
# shellcheck source=scripts/python_env.sh
source "$REPO_ROOT/scripts/python_env.sh"
if ! "$PYTHON" -c 'import reduced_dynamics.cli, pinocchio, rosbags, mcap, matplotlib' \
    2>/dev/null; then
  step "install -e . into $VENV (by ${RD_INSTALLER:-uv})"
  rd_pip_install -e "$REPO_ROOT"  # uv unless RD_INSTALLER=pip (scripts/python_env.sh)
fi
rd() { "$PYTHON" -m reduced_dynamics.cli "$@"; }

step "compile: the kernels, a process per CPU (once after an install; later runs load them)"
rd compile

step "validate: reduced model against full dynamics (1 s per momentum class)"
rd validate --duration 1

step "simulate: paper robot, 10 s at 200 Hz, torques flip sign at t = 2 s and 6 s, thruster pulse at t = 5 s"
rd simulate -o "$OUT/recorded" --overwrite --duration 10 --rate 200 --seed 2 \
  --torque constant --torque-hold 4 --torque-scale 0.1 --thruster 5,0.5,20,-10,5,2,-3,4

step "replay: estimator over the recorded bag (noise settings of config/spacecraft.yaml: star tracker and IMU-grade odometry)"
rd replay "$OUT/recorded" -o "$OUT/estimates" --overwrite --plots "$OUT/plots" \
  --summary-json "$OUT/summary.json" --prediction-mode held_torque --params config/spacecraft.yaml

step "predict: where does the base go if the arm executes a planned motion? (10 s plan)"
rd predict --trajectory config/plans/example_plan.yaml --mu 1 0 0 0 0 2 \
  -o "$OUT/planned_base_path.json"

step "done"
echo "output bag: $OUT/estimates   plots: $OUT/plots/*.png   summary: $OUT/summary.json"
