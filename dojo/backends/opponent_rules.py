"""How the `opponent` actor chooses its cell: named, documented rules over the board as it stands.

A rule sees the cells by index: its preference `order` over all of them, the board's `lines` (each a list of cell
indices: three in a row for tic-tac-toe), the cells its own pieces hold and those the robot's hold. It answers a
free cell, or None when the board is full. Rules are pure functions of these, so a replay is exact and each rule
is tested on hand-built boards (tests/backends/test_opponent_rules.py).

- `random`: the first free cell of `order`, which the compiler draws per episode from the plan's seed
  (`dojo.compiler.actor_draws`): uniformly random among the free cells, fixed once the episode is drawn.
- `win_then_block`: complete one of its own lines if a move does (a line it holds but for one free cell), else
  block one of the robot's (a line the robot holds but for one free cell), else the first free cell of `order`
  (the spec's `prefer`, e.g. centre, corners, edges); among several winning or blocking cells, the first of
  `order`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

Rule = Callable[[Sequence[int], Sequence[Sequence[int]], set[int], set[int]], int | None]


def first_free(order: Sequence[int], taken: set[int]) -> int | None:
    """The first cell of `order` that holds no piece."""
    return next((c for c in order if c not in taken), None)


def completing(order: Sequence[int], lines: Sequence[Sequence[int]], holder: set[int], taken: set[int]
               ) -> int | None:
    """The first cell of `order` that completes a line `holder` holds but for that one free cell."""
    wanted = set()
    for line in lines:
        free = [c for c in line if c not in taken]
        if len(free) == 1 and all(c in holder for c in line if c != free[0]):
            wanted.add(free[0])
    return next((c for c in order if c in wanted), None)


def random_rule(order: Sequence[int], lines: Sequence[Sequence[int]], own: set[int], robot: set[int]) -> int | None:
    return first_free(order, own | robot)


def win_then_block(order: Sequence[int], lines: Sequence[Sequence[int]], own: set[int], robot: set[int]
                   ) -> int | None:
    taken = own | robot
    for holder in (own, robot):
        cell = completing(order, lines, holder, taken)
        if cell is not None:
            return cell
    return first_free(order, taken)


RULES: dict[str, Rule] = {"random": random_rule, "win_then_block": win_then_block}
"""Rule name (the spec's `rule`) -> how it chooses (see the module docstring)."""
