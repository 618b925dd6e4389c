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

# Regenerate the small simulated bags shipped under test/data:
#   ./scripts/make_test_bags.sh [OUT_DIR]        (default OUT_DIR: test/data)
#
# test/test_simulator.py reads the `simulate` lines below (one per bag, no line
# continuations, "$OUT" for the output directory, paths relative to the repository
# root) and checks that they reproduce the shipped bags.

set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
PYTHON="${PYTHON:-python3}"
OUT="${1:-test/data}"
mkdir -p "$OUT"

simulate() { "$PYTHON" -m reduced_dynamics.cli simulate "$@"; }

# Paper robot, /odom, sinusoid torques, one thruster pulse (noise-free sensors).
simulate -o "$OUT/paper_thruster" --summary "$OUT/paper_thruster.summary.json" --overwrite --duration 4 --rate 200 --seed 1 --torque sinusoid --thruster 1.5,0.5,20,-10,5,2,-3,4

# Planar testbed (SE(2) base, gravity normal to the plane), /base_pose only, PD torques,
# noise, drops and the custom-typed /simulator/status topic.
simulate -o "$OUT/planar_pose_only" --summary "$OUT/planar_pose_only.summary.json" --overwrite --urdf config/robots/planar_testbed.urdf --base-joint planar --gravity 0 0 -9.81 --duration 3 --rate 100 --seed 2 --torque pd --base-pose-only --status --noise-position 0.001 --noise-velocity 0.005 --noise-pose 0.002 --drop-rate 0.05

# Paper robot, pure angular momentum, piecewise-constant torques held 1 s (prediction tests).
simulate -o "$OUT/paper_constant" --summary "$OUT/paper_constant.summary.json" --overwrite --duration 3 --rate 100 --seed 3 --torque constant --torque-hold 1 --momentum-class pure_angular
