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
Chi-square quantiles for the filter's gates and tests, from ``scipy.special``.

``scipy.stats`` costs a quarter of a second of imports for one function; the
inverse survival function it calls is ``scipy.special.chdtri``, the same number
bit for bit. :data:`chi2` keeps the ``scipy.stats.chi2.isf`` call shape.
"""

from __future__ import annotations

from scipy.special import chdtri


class _ChiSquare:
    """The one ``scipy.stats.chi2`` method the package uses."""

    @staticmethod
    def isf(probability: float, dof: int) -> float:
        """Return x with P(chi2_dof > x) = ``probability`` (``scipy.stats.chi2.isf``)."""
        return float(chdtri(dof, probability))


#: ``chi2.isf(probability, dof)``, as ``scipy.stats.chi2.isf`` for scalars.
chi2 = _ChiSquare()
