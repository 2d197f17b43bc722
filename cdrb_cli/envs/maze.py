"""Grid mazes: the map text format, stock layouts, geometry (cells <-> metres, wall boxes), shortest paths.

Map files are rows of ``#`` wall, ``.`` free, ``S`` start cell, ``G`` goal cell and ``C`` start-and-goal cell; lines
starting with ``//`` or ``# `` (hash + space) are comments; blank lines are ignored. Cell (i, j) has its centre at
x = (j + 0.5) s - W s / 2 and y = H s / 2 - (i + 0.5) s (the gymnasium-robotics convention, s = cell size).
"""

from __future__ import annotations

from collections import deque
from functools import cached_property
from importlib import resources
from pathlib import Path

import numpy as np

from cdrb_cli.envs.spec import MAP_CHARS, BoxObstacles, MazeLayout
from cdrb_cli.errors import BadInput

STOCK_LAYOUTS = ("maze", "maze-tight", "umaze", "medium", "large")
MAX_CELLS = 100 * 100


def _is_comment(line: str) -> bool:
    return line.startswith("//") or line.startswith("# ")


def parse_map(text: str, name: str, source: str = "<map>") -> MazeLayout:
    """Parse map text into a :class:`MazeLayout`; every problem is a one-line :class:`BadInput` naming the line."""
    rows: list[tuple[int, str]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.rstrip()
        if not line.strip() or _is_comment(line):
            continue
        rows.append((lineno, line.strip()))
    if not rows:
        raise BadInput(f"{source}: the map is empty", hint="write rows of # . S G, one per line")
    width = len(rows[0][1])
    for lineno, row in rows:
        if len(row) != width:
            raise BadInput(
                f"{source}:{lineno}: row has {len(row)} cells but the first row has {width} (ragged rows)",
                hint="every row must have the same number of cells",
            )
        for col, ch in enumerate(row, start=1):
            if ch not in MAP_CHARS:
                raise BadInput(
                    f"{source}:{lineno}:{col}: unknown map character {ch!r}",
                    hint="use # wall, . free, S start, G goal, C start+goal",
                )
    if len(rows) * width > MAX_CELLS:
        raise BadInput(f"{source}: map has {len(rows) * width} cells, more than {MAX_CELLS}", hint="use a smaller map")
    if len(rows) < 3 or width < 3:
        raise BadInput(f"{source}: map must be at least 3x3 cells", hint="add rows or columns")
    cells = "".join(r for _, r in rows)
    if not any(c in "SC" for c in cells):
        raise BadInput(f"{source}: map has no start cell", hint="mark at least one free cell with S (or C)")
    if not any(c in "GC" for c in cells):
        raise BadInput(f"{source}: map has no goal cell", hint="mark at least one free cell with G (or C)")
    layout = MazeLayout(name=name, rows=[r for _, r in rows])
    geom = MazeGeometry(layout)
    starts, goals = geom.start_cells, geom.goal_cells
    reachable = geom.reachable_from(starts[0])
    if not any(tuple(g) in reachable for g in goals):
        raise BadInput(f"{source}: no goal cell can be reached from start cell {tuple(starts[0])}", hint="open a path")
    return layout


def load_map_file(path: str | Path) -> MazeLayout:
    path = Path(path)
    if not path.exists():
        raise BadInput(f"--maze-map {path}: no such file", hint="check the path")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInput(
            f"--maze-map {path}: cannot read it as text ({type(exc).__name__})", hint="pass a text file"
        ) from None
    return parse_map(text, name=path.stem, source=str(path))


def stock_layout(name: str) -> MazeLayout:
    text = resources.files("cdrb_cli.envs.maps").joinpath(f"{name}.txt").read_text()
    return parse_map(text, name=name, source=f"stock map {name}")


class MazeGeometry:
    """Derived geometry of a :class:`MazeLayout` (never stored; rebuilt from the layout)."""

    def __init__(self, layout: MazeLayout):
        self.layout = layout
        self.grid = np.array([list(r) for r in layout.rows])
        self.s = float(layout.cell_size)
        self.n_rows, self.n_cols = self.grid.shape

    # -------------------------------------------------------------- cells
    @cached_property
    def free(self) -> np.ndarray:
        return self.grid != "#"

    @cached_property
    def start_cells(self) -> np.ndarray:
        return np.argwhere(np.isin(self.grid, ["S", "C"]))

    @cached_property
    def goal_cells(self) -> np.ndarray:
        return np.argwhere(np.isin(self.grid, ["G", "C"]))

    def cell_to_xy(self, cells) -> np.ndarray:
        cells = np.asarray(cells, dtype=np.float64)
        x = (cells[..., 1] + 0.5) * self.s - self.n_cols * self.s / 2
        y = self.n_rows * self.s / 2 - (cells[..., 0] + 0.5) * self.s
        return np.stack([x, y], axis=-1)

    def xy_to_cell(self, xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        j = np.floor((xy[..., 0] + self.n_cols * self.s / 2) / self.s)
        i = np.floor((self.n_rows * self.s / 2 - xy[..., 1]) / self.s)
        return np.stack([i, j], axis=-1).astype(np.int64)

    def neighbours(self, cell):
        i, j = int(cell[0]), int(cell[1])
        for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            a, b = i + di, j + dj
            if 0 <= a < self.n_rows and 0 <= b < self.n_cols and self.free[a, b]:
                yield (a, b)

    def bfs(self, source) -> np.ndarray:
        """Grid distances (in cells, 4-connected) from ``source``; -1 where unreachable."""
        dist = np.full(self.grid.shape, -1, dtype=np.int64)
        src = (int(source[0]), int(source[1]))
        dist[src] = 0
        queue = deque([src])
        while queue:
            c = queue.popleft()
            for n in self.neighbours(c):
                if dist[n] < 0:
                    dist[n] = dist[c] + 1
                    queue.append(n)
        return dist

    def reachable_from(self, cell) -> set[tuple[int, int]]:
        d = self.bfs(cell)
        return {(int(a), int(b)) for a, b in np.argwhere(d >= 0)}

    def longest_start_goal_path(self) -> int:
        """The largest grid distance (cells) from any start cell to any goal cell reachable from it."""
        best = 0
        for g in self.goal_cells:
            d = self.bfs(g)
            vals = d[tuple(self.start_cells.T)]
            vals = vals[vals >= 0]
            if vals.size:
                best = max(best, int(vals.max()))
        return best

    # -------------------------------------------------------------- walls
    @cached_property
    def wall_boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """Wall cells merged into horizontal runs: (centers (M, 2), half_sizes (M, 2)) in metres."""
        centers, halves = [], []
        for i in range(self.n_rows):
            j = 0
            while j < self.n_cols:
                if self.grid[i, j] == "#":
                    k = j
                    while k + 1 < self.n_cols and self.grid[i, k + 1] == "#":
                        k += 1
                    c = (self.cell_to_xy([i, j]) + self.cell_to_xy([i, k])) / 2
                    centers.append(c)
                    halves.append([(k - j + 1) * self.s / 2, self.s / 2])
                    j = k + 1
                else:
                    j += 1
        return np.array(centers, dtype=np.float64).reshape(-1, 2), np.array(halves, dtype=np.float64).reshape(-1, 2)

    def obstacles(self, agent_radius: float) -> BoxObstacles:
        c, h = self.wall_boxes
        half_w, half_h = self.n_cols * self.s / 2, self.n_rows * self.s / 2
        return BoxObstacles(
            dims=[0, 1],
            centers=c.round(9).tolist(),
            half_sizes=h.round(9).tolist(),
            inflate=agent_radius,
            low=[-half_w, -half_h],
            high=[half_w, half_h],
        )


def box_distance(points: np.ndarray, centers: np.ndarray, half_sizes: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """Euclidean distance from each point (..., d) to the nearest box (0 inside a box). Vectorized, chunked."""
    pts = np.asarray(points, dtype=np.float64)
    flat = pts.reshape(-1, pts.shape[-1])
    out = np.empty(flat.shape[0], dtype=np.float64)
    if centers.shape[0] == 0:
        out[:] = np.inf
        return out.reshape(pts.shape[:-1])
    for a in range(0, flat.shape[0], chunk):
        p = flat[a : a + chunk]
        gap = np.abs(p[:, None, :] - centers[None]) - half_sizes[None]  # (n, M, d)
        d = np.sqrt(np.square(np.maximum(gap, 0.0)).sum(-1))
        out[a : a + chunk] = d.min(axis=1)
    return out.reshape(pts.shape[:-1])


def in_collision(states: np.ndarray, obstacles: BoxObstacles) -> np.ndarray:
    """Boolean mask over states (..., D): True where the agent (a ball of radius ``obstacles.inflate`` centred at
    the state's obstacle dimensions) overlaps a wall box, or its centre lies outside the map bounds."""
    states = np.asarray(states)
    pts = states[..., obstacles.dims].astype(np.float64)
    centers = np.asarray(obstacles.centers, dtype=np.float64).reshape(-1, len(obstacles.dims))
    halves = np.asarray(obstacles.half_sizes, dtype=np.float64).reshape(-1, len(obstacles.dims))
    hit = box_distance(pts, centers, halves) < obstacles.inflate
    low, high = np.asarray(obstacles.low), np.asarray(obstacles.high)
    outside = np.any((pts < low) | (pts > high), axis=-1)
    return hit | outside
