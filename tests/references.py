"""Obviously-correct reference implementations shared by the tests (no speed, no cleverness)."""

import math


def naive_tour(g, cells):
    """Nearest-neighbour open path from ``cells[0]`` over grid positions ``g`` (L x 2), ties to
    the lowest cell index; returns ``(cost by exact summation, visiting order)``."""
    cur, rest, order, steps = cells[0], set(cells[1:]), [cells[0]], []
    while rest:
        nxt = min(rest, key=lambda c: ((g[c, 0] - g[cur, 0]) ** 2 + (g[c, 1] - g[cur, 1]) ** 2, c))
        steps.append(math.dist(g[cur], g[nxt]))
        rest.remove(nxt)
        order.append(nxt)
        cur = nxt
    return math.fsum(steps), order
