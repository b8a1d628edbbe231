"""dfusion.linalg's chi-square tail and quantile (no scipy in the library path) against scipy.stats.chi2."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from dfusion.errors import ValidationError
from dfusion.linalg import chi2_isf, chi2_sf

DOFS = [*range(1, 41), 63, 64, 99, 100, 255, 256, 1001, 4000]


@pytest.mark.parametrize("dof", DOFS)
def test_chi2_sf_equals_scipy_from_the_body_to_the_far_tail(dof):
    xs = np.concatenate([[1e-6, 0.1, 1.0], dof * np.array([0.25, 0.5, 1.0, 1.5, 2.0, 3.0]), [dof + 200.0]])
    for x in xs:
        ref = float(chi2.sf(x, dof))
        if ref < 1e-300:   # beyond double precision (dof 4000 at three times its mean): both underflow
            assert 0.0 <= chi2_sf(x, dof) < 1e-300, (x, dof)
            continue
        assert chi2_sf(x, dof) == pytest.approx(ref, rel=1e-11, abs=0.0), (x, dof)
    assert chi2_sf(0.0, dof) == 1.0 and chi2_sf(-1.0, dof) == 1.0


@pytest.mark.parametrize("dof", DOFS)
def test_chi2_isf_equals_scipy_for_gate_and_test_probabilities(dof):
    for alpha in (1e-15, 1e-9, 1e-6, 1e-3, 0.01, 0.05, 0.1, 0.3, 0.5, 0.9):
        ref = float(chi2.isf(alpha, dof))
        assert chi2_isf(alpha, dof) == pytest.approx(ref, rel=1e-12), (alpha, dof)


def test_chi2_isf_closed_form_for_two_degrees_of_freedom():
    # Q(x; 2) = exp(-x/2): the quantile is -2 ln(alpha)
    for alpha in (1e-12, 1e-3, 0.2, 0.7):
        assert chi2_isf(alpha, 2) == pytest.approx(-2.0 * math.log(alpha), rel=1e-13)


def test_chi2_isf_rejects_bad_arguments():
    for alpha in (0.0, 1.0, -0.1, float("nan")):
        with pytest.raises(ValidationError):
            chi2_isf(alpha, 3)
    for dof in (0, -2, 2.5, True):
        with pytest.raises(ValidationError):
            chi2_isf(0.01, dof)
