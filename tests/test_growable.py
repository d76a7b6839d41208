"""Growable per-keyframe arrays: capacity by a quarter, rows kept across growth."""

import numpy as np

from common.growable import Rows, grown, grown_capacity


def test_capacity_grows_by_a_quarter_and_always_fits():
    assert grown_capacity(0, 1) == 64
    assert grown_capacity(1000, 1001) == 1250
    assert grown_capacity(1000, 5000) == 5000


def test_grown_keeps_the_rows_and_fills_the_new_ones():
    a = np.arange(6, dtype=np.int32).reshape(3, 2)
    assert grown(a, 3) is a
    b = grown(a, 4, fill=-1)
    assert b.dtype == np.int32 and len(b) == 64
    assert np.array_equal(b[:3], a) and np.all(b[3:] == -1)


def test_rows_append_view_and_drop():
    r = Rows(3, np.int64)
    for i in range(200):
        r.append((i, 2 * i, 3 * i))
    assert len(r) == 200 and r.nbytes < 1.25 * 200 * 3 * 8 + 1
    assert r[150].tolist() == [150, 300, 450]
    r.drop(0)
    r.drop(149 - 1)  # the row of 149, one place up after the first drop
    ids = r.view()[:, 0].tolist()
    assert len(r) == 198 and ids[0] == 1 and 149 not in ids and ids[-1] == 199
    r.append((7, 7, 7))
    assert r[-1].tolist() == [7, 7, 7]
