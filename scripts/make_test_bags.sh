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

# Realistic sensors (issue 10): the paper robot with Odometry from spacecraft-grade sensors:
# attitude 0.5 mrad and position 1 mm (star tracker, relative navigation), twist 2e-3
# (IMU-grade), encoders 1e-4 rad quantised to 1e-5 rad (a 19-bit encoder), tachometers
# 5e-3 rad/s, motor-current efforts 0.05 N m; header stamps with 0.3 ms jitter, records
# 4 +- 1 ms later, 1 % of messages lost; one 0.5 s thruster pulse at 3 s.
simulate -o "$OUT/paper_realistic" --summary "$OUT/paper_realistic.summary.json" --overwrite --duration 6 --rate 100 --seed 4 --torque sinusoid --thruster 3,0.5,20,-10,5,2,-3,4 --noise-position 1e-4 --noise-velocity 0.005 --noise-effort 0.05 --noise-pose 0.001 --noise-orientation 0.0005 --noise-twist 0.002 --quantize joint_position=1e-5 --stamp-jitter 0.0003 --latency 0.004 --latency-jitter 0.001 --drop-rate 0.01

# The same robot and pulse with a spacecraft's navigation (the sensor classes of
# config/spacecraft.yaml): star tracker 5e-5 rad, relative navigation / GNSS position 0.1 m,
# IMU-aided velocity 1e-3 m/s, gyro 1e-4 rad/s, resolver-grade joint rates 1e-3 rad/s;
# encoders, efforts, stamp jitter, latency and drops as paper_realistic; coasting (no
# external wrench) outside [3, 3.5) s.
simulate -o "$OUT/paper_spacecraft" --summary "$OUT/paper_spacecraft.summary.json" --overwrite --duration 6 --rate 100 --seed 8 --torque sinusoid --thruster 3,0.5,20,-10,5,2,-3,4 --noise-position 1e-4 --noise-velocity 0.001 --noise-effort 0.05 --noise-pose 0.1 --noise-orientation 5e-5 --noise-twist 0.001 --noise-twist-angular 1e-4 --quantize joint_position=1e-5 --stamp-jitter 0.0003 --latency 0.004 --latency-jitter 0.001 --drop-rate 0.01

# A planar free-flyer like the freeflyer2 testbed (16 kg, 0.18 kg m^2, no arm), mocap poses
# only at 120 Hz: 0.5 mm and 2 mrad noise, positions quantised to 0.1 mm, 0.5 ms stamp
# jitter, 1 % of the stamps bunched with the next one (gaps of 15-45 us, as in the real
# bags), 3 +- 1 ms latency, outages of ~40 ms at 0.2 per second; the 8 binary 0.2 N thrusters
# fire four times (the rest is coasting), delivering 0.9 / 0.85 / 0.95 of the commanded
# Fx / Fy / Mz; /commanded_wrench at 8 Hz and at every switch.
simulate -o "$OUT/freeflyer_realistic" --summary "$OUT/freeflyer_realistic.summary.json" --overwrite --urdf config/robots/freeflyer.urdf --duration 15 --rate 120 --seed 5 --torque zero --base-pose-only --noise-pose 0.0005 --noise-orientation 0.002 --quantize base_position=1e-4 --stamp-jitter 0.0005 --bunch-fraction 0.01 --latency 0.003 --latency-jitter 0.001 --outage-rate 0.2 --outage-duration 0.04 --thruster-layout freeflyer --fire 2,1,2,5 --fire 5,1.5,4,7 --fire 9,0.8,1,3,5,7 --fire 12,1,6,1 --thrust-gain 0.9 0.85 1 1 1 0.95 --command-rate 8

# The same free-flyer and firings with the mocap noise measured on the freeflyer2 recordings
# (frame to frame: 22-26 um and 0.19-0.22 mrad, thrust_correlation.mocap_noise; no
# quantisation), stamps and outages as freeflyer_realistic.
simulate -o "$OUT/freeflyer_testbed" --summary "$OUT/freeflyer_testbed.summary.json" --overwrite --urdf config/robots/freeflyer.urdf --duration 15 --rate 120 --seed 5 --torque zero --base-pose-only --noise-pose 2.5e-5 --noise-orientation 2e-4 --stamp-jitter 0.0005 --bunch-fraction 0.01 --latency 0.003 --latency-jitter 0.001 --outage-rate 0.2 --outage-duration 0.04 --thruster-layout freeflyer --fire 2,1,2,5 --fire 5,1.5,4,7 --fire 9,0.8,1,3,5,7 --fire 12,1,6,1 --thrust-gain 0.9 0.85 1 1 1 0.95 --command-rate 8

# The filter settings of the realistic bags as a user gets them (docs/events.md "Events on the
# realistic simulated bags"): `tune` with its defaults on each bag. The sensor figures the
# simulation used are written by hand in test/data/*_realistic.sensors.yaml.
"$PYTHON" -m reduced_dynamics.cli tune "$OUT/paper_realistic" -o "$OUT/paper_realistic.tuned.yaml" --quiet > /dev/null
"$PYTHON" -m reduced_dynamics.cli tune "$OUT/freeflyer_realistic" -o "$OUT/freeflyer_realistic.tuned.yaml" --urdf config/robots/freeflyer.urdf --base-pose-topic /base_pose --quiet > /dev/null
"$PYTHON" -m reduced_dynamics.cli tune "$OUT/freeflyer_testbed" -o "$OUT/freeflyer_testbed.tuned.yaml" --urdf config/robots/freeflyer.urdf --base-pose-topic /base_pose --quiet > /dev/null
