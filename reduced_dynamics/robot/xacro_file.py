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


"""
xacro robot descriptions: ``*.xacro`` files expanded to URDF with the ``xacro`` package.

ROS robots are kept as xacro (macros, properties, includes, ``<xacro:arg>``). A
path ending in ``.xacro`` is expanded by the ``xacro`` package (PyPI / ROS), with
``name:=value`` arguments as on xacro's own command line; includes resolve as
xacro resolves them (relative to the including file, ``$(find pkg)`` with a ROS
environment).
"""

from __future__ import annotations

import contextlib
import io
import os
from typing import Mapping, Optional, Sequence

XACRO_SUFFIX = '.xacro'


class XacroError(ValueError):
    """A xacro description that cannot be expanded (one line, with the reason)."""


def is_xacro(source: str) -> bool:
    """Return whether ``source`` names a xacro file (not XML text)."""
    text = str(source)
    return not text.lstrip().startswith('<') and text.endswith(XACRO_SUFFIX)


def parse_xacro_args(items: Optional[Sequence[str]]) -> dict[str, str]:
    """Return ``{name: value}`` of ``name:=value`` items (XacroError on another form)."""
    args: dict[str, str] = {}
    for item in items or ():
        name, sep, value = item.partition(':=')
        if not sep or not name.strip():
            raise XacroError(f'xacro argument {item!r} is not of the form name:=value')
        args[name.strip()] = value
    return args


def expand_xacro(path: str, args: Optional[Mapping[str, str]] = None) -> str:
    """Return the URDF XML of the xacro file at ``path`` expanded with ``args``."""
    if not os.path.isfile(path):
        raise XacroError(f'xacro file not found: {path}')
    try:
        import xacro
    except ImportError as error:
        raise XacroError(f'{path} is a xacro description and the xacro package is not '
                         'installed: pip install xacro (or apt install ros-jazzy-xacro)'
                         ) from error
    # xacro prints warnings and errors itself; they belong in the one-line message.
    chatter = io.StringIO()
    try:
        with contextlib.redirect_stderr(chatter):
            document = xacro.process_file(os.path.abspath(path),
                                          mappings=dict(args or {}))
    except Exception as error:  # XacroException, XML parse and evaluation errors
        text = ' '.join(str(error).split()) or type(error).__name__
        raise XacroError(f'cannot expand xacro {path}: {text}') from error
    finally:
        # xacro keeps per-run state in module globals; a failed run must not leak it.
        xacro.init_stacks(None)
    return document.toxml()
