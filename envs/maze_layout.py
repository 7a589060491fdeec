"""Maze layouts: text maps, D4RL coordinates, merged wall boxes, wall tests and start sampling.

A map is a block of text, one line per row, one character per cell:

    ``1`` or ``#``  wall          ``0`` or ``.``  free
    ``r`` or ``s``  the start     ``g``           the goal

Coordinates follow D4RL: cell (row i, col j) has its centre at
``x = (j - j0) * cell_size, y = (i - i0) * cell_size`` where (i0, j0) is the origin cell, by
default the start cell (so the start is at (0, 0)). Everything outside the map counts as wall; a
map whose border is not all wall gets a ring of wall cells added around it.
"""
from __future__ import annotations

import collections
import dataclasses
from typing import Optional, Sequence, Tuple

import jax
import jax.numpy as jnp
import numpy as np

WALL_CHARS = "1#"
FREE_CHARS = "0."
START_CHARS = "rsRS"
GOAL_CHARS = "gG"
VALID_CHARS = WALL_CHARS + FREE_CHARS + START_CHARS + GOAL_CHARS


def _rows(*rows: Sequence) -> str:
    return "\n".join("".join(str(c) for c in row) for row in rows)


# The built-in maps (see the "Tasks" table of the docs): D4RL U_MAZE_TEST, BIG_MAZE_TEST,
# HARDEST_MAZE_TEST, the HIRO-style four rooms and the open Ant-Reacher arena.
U_MAZE = _rows(
    [1, 1, 1, 1, 1],
    [1, "r", 0, 0, 1],
    [1, 1, 1, 0, 1],
    [1, "g", 0, 0, 1],
    [1, 1, 1, 1, 1],
)
MEDIUM_MAZE = _rows(
    [1, 1, 1, 1, 1, 1, 1, 1],
    [1, "r", 0, 1, 1, 0, 0, 1],
    [1, 0, 0, 1, 0, 0, 0, 1],
    [1, 1, 0, 0, 0, 1, 1, 1],
    [1, 0, 0, 1, 0, 0, 0, 1],
    [1, 0, 1, 0, 0, 1, 0, 1],
    [1, 0, 0, 0, 1, 0, "g", 1],
    [1, 1, 1, 1, 1, 1, 1, 1],
)
LARGE_MAZE = _rows(
    [1] * 12,
    [1, "r", 0, 0, 0, 1, 0, 0, 0, 0, 0, 1],
    [1, 0, 1, 1, 0, 1, 0, 1, 0, 1, 0, 1],
    [1, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 1],
    [1, 0, 1, 1, 1, 1, 0, 1, 1, 1, 0, 1],
    [1, 0, 0, 1, 0, 1, 0, 0, 0, 0, 0, 1],
    [1, 1, 0, 1, 0, 1, 0, 1, 0, 1, 1, 1],
    [1, 0, 0, 1, 0, 0, 0, 1, 0, "g", 0, 1],
    [1] * 12,
)
FOUR_ROOMS = _rows(
    [1, 1, 1, 1, 1, 1, 1, 1, 1],
    [1, 0, 0, 0, 1, 0, 0, 0, 1],
    [1, 0, "r", 0, 0, 0, 0, 0, 1],
    [1, 0, 0, 0, 1, 0, 0, 0, 1],
    [1, 1, 0, 1, 1, 1, 0, 1, 1],
    [1, 0, 0, 0, 1, 0, 0, 0, 1],
    [1, 0, 0, 0, 0, 0, "g", 0, 1],
    [1, 0, 0, 0, 1, 0, 0, 0, 1],
    [1, 1, 1, 1, 1, 1, 1, 1, 1],
)
# Open 9x9 arena (free space (-10.5, 10.5)^2), goal at the centre (0, 0). The map's start is the
# test corner (9, 9); training starts come from the diverse-start sampler (uniform over the arena).
ANT_REACHER = _rows(
    [1] * 9,
    [1, 0, 0, 0, 0, 0, 0, 0, 1],
    [1, 0, 0, 0, 0, 0, 0, 0, 1],
    [1, 0, 0, 0, 0, 0, 0, 0, 1],
    [1, 0, 0, 0, "g", 0, 0, 0, 1],
    [1, 0, 0, 0, 0, 0, 0, 0, 1],
    [1, 0, 0, 0, 0, 0, 0, 0, 1],
    [1, 0, 0, 0, 0, 0, 0, "r", 1],
    [1] * 9,
)

# name -> (map, cell size, origin cell or None for "the start cell")
BUILTIN_MAPS = {
    "u_maze": (U_MAZE, 4.0, None),
    "medium": (MEDIUM_MAZE, 4.0, None),
    "large": (LARGE_MAZE, 4.0, None),
    "four_rooms": (FOUR_ROOMS, 3.0, None),
    "ant_reacher": (ANT_REACHER, 3.0, (4, 4)),
}


@dataclasses.dataclass(frozen=True)
class MazeLayout:
    """A parsed maze. Hashable (tuples only), so it can be a static argument / config field.

    wall_boxes: ((cx, cy, hx, hy), ...) axis-aligned boxes (centre, half sizes) whose union is exactly
    the set of wall cells. bounds: (xmin, xmax, ymin, ymax) of the whole map.
    free_cells: centres (x, y) of all non-wall cells.
    """

    name: str
    cell_size: float
    rows: Tuple[str, ...]
    origin: Tuple[int, int]  # (row, col) of the cell at (0, 0)
    start_cell: Tuple[int, int]
    goal_cell: Tuple[int, int]
    start_xy: Tuple[float, float]
    goal_xy: Tuple[float, float]
    wall_boxes: Tuple[Tuple[float, float, float, float], ...]
    bounds: Tuple[float, float, float, float]
    free_cells: Tuple[Tuple[float, float], ...]

    # ---- geometry helpers ---------------------------------------------------------------------
    @property
    def shape(self) -> Tuple[int, int]:
        return len(self.rows), len(self.rows[0])

    def cell_center(self, i: int, j: int) -> Tuple[float, float]:
        return ((j - self.origin[1]) * self.cell_size, (i - self.origin[0]) * self.cell_size)

    def wall_grid(self) -> np.ndarray:
        """(rows, cols) bool array, True for wall cells."""
        return np.array([[c in WALL_CHARS for c in row] for row in self.rows])

    def xy_to_cell(self, xy):
        """(..., 2) positions -> (..., 2) int (row, col) indices (may lie outside the map)."""
        xy = jnp.asarray(xy)
        col = jnp.floor(xy[..., 0] / self.cell_size + 0.5).astype(jnp.int32) + self.origin[1]
        row = jnp.floor(xy[..., 1] / self.cell_size + 0.5).astype(jnp.int32) + self.origin[0]
        return jnp.stack([row, col], axis=-1)

    def in_wall(self, xy, margin: float = 0.0):
        """(..., 2) positions -> (...,) bool: inside a wall cell (grown by `margin`) or off the map.

        Pure jnp, jit- and vmap-able.
        """
        xy = jnp.asarray(xy)
        boxes = jnp.asarray(self.wall_boxes, dtype=xy.dtype if jnp.issubdtype(xy.dtype, jnp.floating) else jnp.float32)
        d = jnp.abs(xy[..., None, :] - boxes[:, :2]) - boxes[:, 2:] - margin  # (..., K, 2)
        inside = jnp.any(jnp.all(d < 0.0, axis=-1), axis=-1)
        xmin, xmax, ymin, ymax = self.bounds
        off = ((xy[..., 0] < xmin + margin) | (xy[..., 0] > xmax - margin)
               | (xy[..., 1] < ymin + margin) | (xy[..., 1] > ymax - margin))
        return inside | off

    def sample_free(self, key, goal_xy=None, *, margin: float = 0.5, goal_tolerance: float = 0.6,
                    num_candidates: int = 128):
        """One position uniform over free space, at least `margin` from every wall and farther than
        `goal_tolerance` from the goal. Fixed-shape rejection: draws `num_candidates` cell-then-offset
        proposals and keeps the first valid one (falls back to the start if none is, which needs a
        valid fraction of free space below ~5%).
        """
        goal = jnp.asarray(self.goal_xy if goal_xy is None else goal_xy, jnp.float32)
        cells = jnp.asarray(self.free_cells, jnp.float32)
        k_cell, k_off = jax.random.split(key)
        idx = jax.random.randint(k_cell, (num_candidates,), 0, cells.shape[0])
        off = jax.random.uniform(k_off, (num_candidates, 2), minval=-0.5, maxval=0.5) * self.cell_size
        cand = cells[idx] + off
        ok = ~self.in_wall(cand, margin) & (jnp.linalg.norm(cand - goal, axis=-1) > goal_tolerance)
        first = jnp.argmax(ok)
        return jnp.where(jnp.any(ok), cand[first], jnp.asarray(self.start_xy, jnp.float32))


# ---- parsing --------------------------------------------------------------------------------------
def _merge_boxes(wall: np.ndarray):
    """Greedy rectangle cover of the wall cells: grow right, then down. Returns (i, j, h, w) list."""
    used = np.zeros_like(wall)
    rects = []
    n_rows, n_cols = wall.shape
    for i in range(n_rows):
        for j in range(n_cols):
            if not wall[i, j] or used[i, j]:
                continue
            w = 1
            while j + w < n_cols and wall[i, j + w] and not used[i, j + w]:
                w += 1
            h = 1
            while i + h < n_rows and np.all(wall[i + h, j:j + w]) and not np.any(used[i + h, j:j + w]):
                h += 1
            used[i:i + h, j:j + w] = True
            rects.append((i, j, h, w))
    return rects


def parse_map(map_text: str, cell_size: float, name: str = "custom",
              origin: Optional[Tuple[int, int]] = None, start_xy=None, goal_xy=None) -> MazeLayout:
    """Parse a text map into a `MazeLayout`, raising a `ValueError` that names what to fix.

    start_xy / goal_xy optionally move the start / goal to exact coordinates (they must lie in
    free space, and the goal must be reachable from the start).
    """
    if not isinstance(map_text, str):
        raise ValueError(f"map for {name!r} must be a string with one line per row, got {type(map_text).__name__}")
    try:
        cell_size = float(cell_size)
    except (TypeError, ValueError):
        raise ValueError(f"cell_size for {name!r} must be a positive number, got {cell_size!r}") from None
    if not np.isfinite(cell_size) or cell_size <= 0:
        raise ValueError(f"cell_size for {name!r} must be a positive number, got {cell_size!r}")
    lines = [ln.strip() for ln in map_text.strip("\n").splitlines()]
    lines = [ln for ln in lines if ln]
    if not lines:
        raise ValueError(f"map for {name!r} is empty: give one line per row, e.g. '111\\n1r1\\n1g1\\n111'")
    widths = {len(ln) for ln in lines}
    if len(widths) != 1:
        desc = ", ".join(f"row {i}: {len(ln)}" for i, ln in enumerate(lines))
        raise ValueError(f"map for {name!r} has ragged rows (every row needs the same number of cells): {desc}")
    for i, ln in enumerate(lines):
        for j, c in enumerate(ln):
            if c not in VALID_CHARS:
                raise ValueError(
                    f"map for {name!r} has unknown character {c!r} at row {i}, col {j}; use "
                    f"'1'/'#' wall, '0'/'.' free, 'r'/'s' start, 'g' goal")
    starts = [(i, j) for i, ln in enumerate(lines) for j, c in enumerate(ln) if c in START_CHARS]
    goals = [(i, j) for i, ln in enumerate(lines) for j, c in enumerate(ln) if c in GOAL_CHARS]
    if len(starts) == 0:
        raise ValueError(f"map for {name!r} has no start: mark exactly one free cell with 'r'")
    if len(starts) > 1:
        raise ValueError(f"map for {name!r} has several starts at (row, col) {starts}: keep exactly one 'r'")
    if len(goals) == 0:
        raise ValueError(f"map for {name!r} has no goal: mark exactly one free cell with 'g'")
    if len(goals) > 1:
        raise ValueError(f"map for {name!r} has several goals at (row, col) {goals}: keep exactly one 'g'")

    # Pad with a ring of walls unless the border is already all wall.
    border = lines[0] + lines[-1] + "".join(ln[0] + ln[-1] for ln in lines)
    pad = any(c not in WALL_CHARS for c in border)
    if pad:
        w = len(lines[0]) + 2
        lines = ["1" * w] + ["1" + ln + "1" for ln in lines] + ["1" * w]
        starts = [(i + 1, j + 1) for i, j in starts]
        goals = [(i + 1, j + 1) for i, j in goals]
        if origin is not None:
            origin = (origin[0] + 1, origin[1] + 1)
    start_cell, goal_cell = starts[0], goals[0]
    wall = np.array([[c in WALL_CHARS for c in ln] for ln in lines])
    n_rows, n_cols = wall.shape
    if origin is None:
        origin = start_cell
    origin = (int(origin[0]), int(origin[1]))

    S = cell_size

    def center(i, j):
        return (float((j - origin[1]) * S), float((i - origin[0]) * S))

    def to_cell(xy, what):
        try:
            x, y = (float(v) for v in xy)
        except (TypeError, ValueError):
            raise ValueError(f"{what} for {name!r} must be two numbers (x, y), got {xy!r}") from None
        i = int(np.floor(y / S + 0.5)) + origin[0]
        j = int(np.floor(x / S + 0.5)) + origin[1]
        if not (0 <= i < n_rows and 0 <= j < n_cols) or wall[i, j]:
            raise ValueError(f"{what} {(x, y)} of {name!r} lies inside a wall (or off the map): "
                             f"move it to a free cell")
        return (i, j), (x, y)

    start_pos, goal_pos = center(*start_cell), center(*goal_cell)
    if start_xy is not None:
        start_cell, start_pos = to_cell(start_xy, "start")
    if goal_xy is not None:
        goal_cell, goal_pos = to_cell(goal_xy, "goal")

    # Reachability (BFS over 4-connected free cells).
    seen = np.zeros_like(wall)
    queue = collections.deque([start_cell])
    seen[start_cell] = True
    while queue:
        i, j = queue.popleft()
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            a, b = i + di, j + dj
            if 0 <= a < n_rows and 0 <= b < n_cols and not wall[a, b] and not seen[a, b]:
                seen[a, b] = True
                queue.append((a, b))
    if not seen[goal_cell]:
        off = (1, 1) if pad else (0, 0)
        raise ValueError(
            f"map for {name!r}: the goal at (row, col) {(goal_cell[0] - off[0], goal_cell[1] - off[1])} "
            f"cannot be reached from the start at {(start_cell[0] - off[0], start_cell[1] - off[1])}: "
            f"open a path of free cells between them")

    boxes = []
    for i, j, h, w in _merge_boxes(wall):
        cx, cy = center(i + (h - 1) / 2.0, j + (w - 1) / 2.0)
        boxes.append((cx, cy, w * S / 2.0, h * S / 2.0))
    x0, y0 = center(0, 0)
    bounds = (x0 - S / 2, x0 + (n_cols - 0.5) * S, y0 - S / 2, y0 + (n_rows - 0.5) * S)
    free = tuple(center(i, j) for i in range(n_rows) for j in range(n_cols) if not wall[i, j])
    return MazeLayout(
        name=name, cell_size=S, rows=tuple(lines), origin=origin, start_cell=start_cell,
        goal_cell=goal_cell, start_xy=start_pos, goal_xy=goal_pos,
        wall_boxes=tuple(boxes), bounds=bounds, free_cells=free)


def get_layout(name: str, start_xy=None, goal_xy=None) -> MazeLayout:
    """A built-in layout by name ("u_maze", "medium", "large", "four_rooms", "ant_reacher")."""
    if name not in BUILTIN_MAPS:
        raise ValueError(f"unknown maze layout {name!r}; valid layouts: {sorted(BUILTIN_MAPS)}")
    text, size, origin = BUILTIN_MAPS[name]
    return parse_map(text, size, name=name, origin=origin, start_xy=start_xy, goal_xy=goal_xy)
