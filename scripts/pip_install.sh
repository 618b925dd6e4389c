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

# Sourced by scripts/python_env.sh (test.sh, demo.sh) and scripts/check_readme_install.sh:
# defines rd_pip_install, nothing else.

# rd_pip_install ARGS...: `pip install ARGS` into $PYTHON's environment, by uv (from PyPI)
# unless RD_INSTALLER=pip. Measured on this project's 2-core VM with empty caches: the test
# extras (252 distributions) in 14 s with uv, 103 s with pip, the same distributions and
# versions. pip's settings uv does not read are passed on (index, find-links, CA file);
# pip is the fallback when uv cannot be installed or fails.
rd_pip_install() {
  if [ "${RD_INSTALLER:-uv}" = uv ]; then
    if "$PYTHON" -m uv --version >/dev/null 2>&1 || "$PYTHON" -m pip install -q "uv>=0.4"; then
      local uv_args=(-q --python "$PYTHON")
      local index
      index="${PIP_INDEX_URL:-$("$PYTHON" -m pip config get global.index-url 2>/dev/null || true)}"
      [ -z "$index" ] || uv_args+=(--index-url "$index")
      local links
      for links in ${PIP_FIND_LINKS:-}; do
        [ ! -e "$links" ] || uv_args+=(--find-links "$links")
      done
      if (if [ -n "${PIP_CERT:-}" ] && [ -z "${SSL_CERT_FILE:-}" ]; then
            export SSL_CERT_FILE="$PIP_CERT"
          fi
          "$PYTHON" -m uv pip install "${uv_args[@]}" "$@"); then
        return 0
      fi
      echo "WARNING: uv pip install failed; installing with pip instead" >&2
    fi
  fi
  "$PYTHON" -m pip install -q "$@"
}
