"""The statistics every stage reports the same way: per-cause failure counts, sample standard deviations, means
that admit a missing measurement, and confidence intervals. `cdrb eval` summarizes with them, `cdrb report` and `cdrb
select` pool seeds with them."""

from __future__ import annotations

import numpy as np

from cdrb_cli.envs.family import FAILURE_CAUSES

#: per-episode failure codes (``episodes/failure``): 0 a success, i + 1 the cause FAILURE_CAUSES[i]; -1 not measured
#: (an eval from before schema 2.5)
FAILURE_CODES = {"none": 0, **{cause: i + 1 for i, cause in enumerate(FAILURE_CAUSES)}}


def failure_code(success: bool, plan_crossed: bool, execution_failure: str) -> int:
    """The code of an episode's outcome: a success; a plan through an obstacle; else why the execution failed."""
    if success:
        return 0
    return FAILURE_CODES["plan" if plan_crossed else execution_failure]


def failure_counts(codes) -> dict[str, int] | None:
    """Failed episodes per cause (every cause listed, zeros included); None when any episode was not classified."""
    codes = np.asarray(list(codes), dtype=np.int64)
    if (codes < 0).any():
        return None
    return {cause: int((codes == FAILURE_CODES[cause]).sum()) for cause in FAILURE_CAUSES}


def sum_failures(counts) -> dict[str, int] | None:
    """The per-cause sum of several :func:`failure_counts` (None when any is None)."""
    counts = list(counts)
    if not counts or any(c is None for c in counts):
        return None
    return {cause: sum(c[cause] for c in counts) for cause in FAILURE_CAUSES}


def sample_std(values) -> float:
    """The sample standard deviation (ddof = 1) across seeds; 0 for a single seed."""
    v = np.asarray(values, dtype=np.float64)
    return float(v.std(ddof=1)) if v.size > 1 else 0.0


def mean_or_none(values) -> float | None:
    """The mean, or None when there is no value or any is None (a measurement some file did not make)."""
    values = list(values)
    return float(np.mean(values)) if values and all(v is not None for v in values) else None


def std_or_none(values) -> float | None:
    """The sample standard deviation, or None when there is no value or any is None (as :func:`mean_or_none`)."""
    values = list(values)
    return sample_std(values) if values and all(v is not None for v in values) else None


def ci95(values) -> float:
    """Half-width of the 95% confidence interval of the mean over seeds (Student t, n - 1 degrees of freedom);
    0 for a single seed."""
    v = np.asarray(values, dtype=np.float64)
    if v.size < 2:
        return 0.0
    from scipy.stats import t

    return float(t.ppf(0.975, v.size - 1) * v.std(ddof=1) / np.sqrt(v.size))
