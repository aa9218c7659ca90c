"""The tracer's kernels compiled ahead of use (icbtool.trace.warm, run by ``make install``)."""

from __future__ import annotations

import pytest

from icbtool.trace import warm as W


def test_unknown_kernel_names_the_choices():
    with pytest.raises(ValueError, match=r"unknown kernel\(s\) \['mitsuba'\].*general.*lambert"):
        W.warm(("mitsuba",))


def test_warm_leaves_both_kernels_in_numba_s_disk_cache():
    from icbtool.trace import general, kernels

    times = W.warm(jobs=2)
    assert set(times) == set(W.KERNELS) and all(t > 0 for t in times.values())
    for k in (kernels.trace_paths, general.trace_paths_general):
        # what a new process loads instead of compiling: numba's index for the kernel's source
        assert k._cache._cache_file._load_index(), k
