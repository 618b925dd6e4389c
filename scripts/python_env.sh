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

# Sourced by scripts/test.sh and scripts/demo.sh: sets PYTHON to an interpreter pip may
# install into. Expects WS (work folder) and the as_root and step helpers.
# A Debian/Ubuntu system interpreter refuses pip installs (PEP 668): use a venv then.
if "$PYTHON" - <<'EOF'
import os
import sys
import sysconfig
managed = os.path.exists(os.path.join(sysconfig.get_path('stdlib'), 'EXTERNALLY-MANAGED'))
sys.exit(0 if managed and sys.prefix == sys.base_prefix else 1)
EOF
then
  VENV="$WS/venv"
  if [ ! -x "$VENV/bin/python" ]; then
    step "creating $VENV ($PYTHON is externally managed)"
    if ! "$PYTHON" -m venv --system-site-packages "$VENV"; then
      as_root apt-get install -y -q --no-install-recommends python3-venv
      "$PYTHON" -m venv --system-site-packages "$VENV"
    fi
  fi
  PYTHON="$VENV/bin/python"
fi
