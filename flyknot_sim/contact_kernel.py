"""The rope's self-contact scan, compiled (numba).

The lab asks after every physics step of a motion whether the rope touches itself (the
first contact's time goes into the record) and at every tick of the settle which vertices
its self-contacts span. :meth:`flyknot_sim.rope_handle.BoundRope.self_contact_elements`
answers with a dozen small NumPy operations on MuJoCo's contact arrays (~50-70 us a call,
a sixth of a step); :func:`self_contact_span` walks the same arrays once. Integers only,
so its answer is the NumPy scan's exactly; ``tests/test_contact_kernel.py`` holds the two
equal on random contact lists and on the lab's own states.
"""

from __future__ import annotations

import numba

__all__ = ["self_contact_span"]


@numba.njit(cache=True)
def self_contact_span(flex, elem, geom, exclude, ncon, flex_id, end_geom, n):
    """The lowest and highest element of the rope's self-contacts, or (-1, -1) if none.

    A self-contact is an active contact (``exclude == 0``) between two elements i, j of
    flex ``flex_id`` with |i - j| >= 2 (sharing no vertex), or between the end weight (geom
    ``end_geom``, counted as element ``n``) and an element j <= n - 2 of the flex.

    Args:
        flex: Flex ids of the contacts' two sides, (>= ncon, 2) (-1: not a flex).
        elem: Flex element ids of the two sides, (>= ncon, 2).
        geom: Geom ids of the two sides, (>= ncon, 2) (-1: not a geom).
        exclude: MuJoCo's exclusion flag per contact, (>= ncon,) (0: active).
        ncon: Contacts to scan.
        flex_id: The rope's flex.
        end_geom: The end weight's geom (a geom of the model, >= 0: flex sides carry -1).
        n: The rope's element count.
    """
    lo, hi = -1, -1
    for k in range(ncon):
        if exclude[k] != 0:
            continue
        a, b = -1, -1
        if flex[k, 0] == flex_id and flex[k, 1] == flex_id:
            if abs(elem[k, 0] - elem[k, 1]) >= 2:
                a, b = elem[k, 0], elem[k, 1]
        elif geom[k, 0] == end_geom and flex[k, 1] == flex_id and elem[k, 1] <= n - 2:
            a, b = n, elem[k, 1]
        elif geom[k, 1] == end_geom and flex[k, 0] == flex_id and elem[k, 0] <= n - 2:
            a, b = n, elem[k, 0]
        if a < 0:
            continue
        low, high = min(a, b), max(a, b)
        if lo < 0 or low < lo:
            lo = low
        if high > hi:
            hi = high
    return lo, hi
