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
The BLAS thread count of the entry points: one, whatever the machine.

numpy and scipy each ship their own OpenBLAS (two libraries in one process; numba's
compiled ``np.dot`` calls scipy's). With OpenBLAS's default threads (one per core) the
pulse fit at a detection costs several times the CPU, small LAPACK calls are much
slower, and the large products' last bits depend on the thread count: the node's and
replay's outputs would depend on the machine (docs/performance.md, "Stop 26").

The entry points (the CLI's subcommands, the node, replay-many's workers on every
backend) call :func:`limit_blas_threads`; :func:`limited_blas_threads` scopes the same limit
to a library call (:func:`reduced_dynamics.replay.replay`). threadpoolctl changes the
count of the libraries already loaded, so both are loaded first: setting
``OPENBLAS_NUM_THREADS`` in ``os.environ`` works only before numpy loads, and a limit
applied before ``scipy.linalg`` is imported leaves scipy's library at its default
(measured, docs/performance.md).

``REDUCED_DYNAMICS_BLAS_THREADS`` overrides the count: a positive integer, or
``inherit`` to leave the libraries as they loaded (``OPENBLAS_NUM_THREADS`` or
OpenBLAS's default then apply). A user's ``OPENBLAS_NUM_THREADS`` alone does not:
the outputs must not depend on it.
"""

from contextlib import contextmanager
import os
from typing import Iterator, Mapping, Optional

#: The environment variable that overrides the entry points' BLAS thread count.
ENV_BLAS_THREADS = 'REDUCED_DYNAMICS_BLAS_THREADS'

#: Its value that leaves the BLAS libraries' thread counts as they loaded.
INHERIT = 'inherit'


def requested_threads(environ: Optional[Mapping[str, str]] = None) -> Optional[int]:
    """Return the BLAS thread count to set (default 1), or None for ``inherit``."""
    text = (os.environ if environ is None else environ).get(ENV_BLAS_THREADS, '').strip()
    if not text:
        return 1
    if text.lower() == INHERIT:
        return None
    try:
        count = int(text)
    except ValueError:
        count = 0
    if count < 1:
        raise ValueError(f'{ENV_BLAS_THREADS}={text!r}: a positive integer or {INHERIT!r}')
    return count


def _load_blas_libraries() -> None:
    """Load numpy's and scipy's BLAS, so that threadpoolctl finds both."""
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401
    import scipy.linalg.cython_blas  # noqa: F401 (numba's np.dot in compiled code)


def limit_blas_threads(environ: Optional[Mapping[str, str]] = None) -> Optional[int]:
    """Set every loaded BLAS library's thread count for the process; return it (None: inherit)."""
    count = requested_threads(environ)
    if count is not None:
        from threadpoolctl import threadpool_limits
        _load_blas_libraries()
        threadpool_limits(limits=count, user_api='blas')
    return count


@contextmanager
def limited_blas_threads(environ: Optional[Mapping[str, str]] = None) -> Iterator[Optional[int]]:
    """Run the block with :func:`limit_blas_threads`' count; restore the counts after it."""
    count = requested_threads(environ)
    if count is None:
        yield None
        return
    from threadpoolctl import threadpool_limits
    _load_blas_libraries()
    with threadpool_limits(limits=count, user_api='blas'):
        yield count
