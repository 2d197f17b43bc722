"""Grid mazes: the map text format, stock layouts, geometry (cells <-> metres, wall boxes), shortest paths.

Map files are rows of ``#`` wall, ``.`` free, ``S`` start cell, ``G`` goal cell and ``C`` start-and-goal cell; lines
starting with ``//`` or ``# `` (hash + space) are comments; blank lines are ignored. Cell (i, j) has its centre at
x = (j + 0.5) s - W s / 2 and y = H s / 2 - (i + 0.5) s (the gymnasium-robotics convention, s = cell size).
"""

from __future__ import annotations

from collections import deque
from functools import cached_property, lru_cache
from importlib import resources
from pathlib import Path

import numpy as np
from pydantic import Field, field_validator, model_validator

from cdrb_cli.envs.spec import BoxObstacles
from cdrb_cli.errors import BadInput, RunFailed
from cdrb_cli.schema_base import Record

STOCK_LAYOUTS = ("maze", "maze-tight", "umaze", "medium", "large")
MAP_CHARS = {"#": "wall", ".": "free", "S": "start", "G": "goal", "C": "start and goal"}
MAX_MAP_SIDE = 100
MAX_CELLS = MAX_MAP_SIDE * MAX_MAP_SIDE
#: the longest map name (a map file's name without its extension)
MAX_MAP_NAME = 200


def _breaks_lines(text: str) -> bool:
    """Whether ``text`` holds a character that starts a new line (newline, carriage return, U+2028...)."""
    return len(f"x{text}x".splitlines()) > 1


class MazeLayout(Record):
    """A grid maze: ``rows`` of ``#`` wall, ``.`` free, ``S`` start cell, ``G`` goal cell, ``C`` start+goal cell."""

    name: str = Field(max_length=MAX_MAP_NAME)
    rows: list[str] = Field(min_length=3, max_length=MAX_MAP_SIDE)
    cell_size: float = Field(1.0, gt=0, le=100)

    @field_validator("name")
    @classmethod
    def _one_line(cls, name: str) -> str:
        if _breaks_lines(name):
            raise ValueError("a map's name may not hold a line break (it is printed in log lines)")
        return name

    @field_validator("rows")
    @classmethod
    def _check_rows(cls, rows: list[str]) -> list[str]:
        width = len(rows[0])
        if not 3 <= width <= MAX_MAP_SIDE:
            raise ValueError(f"rows must have 3..{MAX_MAP_SIDE} cells (a map too narrow or too wide)")
        if any(len(r) != width for r in rows):
            raise ValueError("rows must all have the same length")
        if any(ch not in MAP_CHARS for r in rows for ch in r):
            raise ValueError(f"rows may only contain {''.join(MAP_CHARS)}")
        return rows

    @model_validator(mode="after")
    def _playable(self) -> MazeLayout:
        """What the protocol needs of any map, held by the record itself (a map file is checked line by line
        first, by :func:`parse_map`; this catches a map edited inside an artifact): a start cell, a goal cell, and
        a start cell that reaches a goal cell other than itself."""
        cells = "".join(self.rows)
        if not any(c in "SC" for c in cells):
            raise ValueError("the map has no start cell (S or C)")
        if not any(c in "GC" for c in cells):
            raise ValueError("the map has no goal cell (G or C)")
        if not _has_pair(tuple(self.rows)):
            raise ValueError("no start cell of the map reaches a goal cell other than itself")
        return self

    @property
    def n_rows(self) -> int:
        return len(self.rows)

    @property
    def n_cols(self) -> int:
        return len(self.rows[0])


def _is_comment(line: str) -> bool:
    return line.startswith("//") or line.startswith("# ")


def _looks_like_row(line: str) -> bool:
    """A ``# `` comment made only of map characters and spaces, holding a start or goal cell (``# S..#``): most
    likely a wall row written with a space after its first ``#``."""
    cells = line.replace(" ", "")
    return set(cells) <= set(MAP_CHARS) and any(c in "SGC" for c in cells)


def parse_map(text: str, name: str, source: str = "<map>") -> MazeLayout:
    """Parse map text into a :class:`MazeLayout`; every problem is a one-line :class:`BadInput` naming the line."""
    rows: list[tuple[int, str]] = []
    row_like: list[int] = []  # comment lines that look like rows, named when the map lacks what they hold
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.rstrip()
        if not line.strip() or _is_comment(line):
            if line.startswith("# ") and _looks_like_row(line):
                row_like.append(lineno)
            continue
        rows.append((lineno, line.strip()))

    def hint(text: str) -> str:
        if not row_like:
            return text
        return (
            f"{text}; line {row_like[0]} is read as a comment (a line starting with '# ' is one): write map rows "
            "without spaces"
        )

    if not rows:
        raise BadInput(f"{source}: the map is empty", hint=hint("write rows of # . S G, one per line"))
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
    # the layout's own bounds, checked here so that a map beyond them is one line naming the file, not a
    # validation error of the record
    if len(rows) > MAX_MAP_SIDE:
        raise BadInput(
            f"{source}: map is too tall: {len(rows)} rows, more than {MAX_MAP_SIDE}",
            hint=f"use at most {MAX_MAP_SIDE} rows",
        )
    if width > MAX_MAP_SIDE:
        raise BadInput(
            f"{source}: map is too wide: {width} cells per row, more than {MAX_MAP_SIDE}",
            hint=f"use at most {MAX_MAP_SIDE} cells per row",
        )
    if len(name) > MAX_MAP_NAME:
        raise BadInput(
            f"{source}: the map's name has {len(name)} characters, more than {MAX_MAP_NAME}",
            hint=f"a map is named after its file: rename the file to at most {MAX_MAP_NAME} characters",
        )
    if _breaks_lines(name):  # printed in log lines and reports (other control characters are shown as ?)
        raise BadInput(
            f"{source}: the map's name {name!r} has a line break",
            hint="a map is named after its file: rename the file without newlines",
        )
    if "+" in name:  # <id>+<scene> names a task in another map: map a.txt in scene b.txt is map:a+b
        raise BadInput(
            f"{source}: the map's name {name!r} has a '+', which joins a map and its scene in ids",
            hint="a map is named after its file: rename the file without '+'",
        )
    if len(rows) * width > MAX_CELLS:
        raise BadInput(f"{source}: map has {len(rows) * width} cells, more than {MAX_CELLS}", hint="use a smaller map")
    if len(rows) < 3 or width < 3:
        raise BadInput(f"{source}: map must be at least 3x3 cells", hint=hint("add rows or columns"))
    cells = "".join(r for _, r in rows)
    if not any(c in "SC" for c in cells):
        raise BadInput(f"{source}: map has no start cell", hint=hint("mark at least one free cell with S (or C)"))
    if not any(c in "GC" for c in cells):
        raise BadInput(f"{source}: map has no goal cell", hint=hint("mark at least one free cell with G (or C)"))
    # the protocol draws a start cell and a different goal cell reachable from it
    if not _has_pair(tuple(r for _, r in rows)):
        raise BadInput(
            f"{source}: no start cell can reach a goal cell other than itself",
            hint=hint("open a path, or mark another goal cell"),
        )
    return MazeLayout(name=name, rows=[r for _, r in rows])


MAX_MAP_BYTES = 1 << 20


def load_map_file(path: str | Path, flag: str = "--maze-map") -> MazeLayout:
    """A map file, read through the guarded reader (a regular text file of at most 1 MiB, no link out of its
    folder) and parsed; every problem is one line naming ``flag`` or the line."""
    from cdrb_cli.files import read_input_text

    path = Path(path)
    if path.suffix.lower() in (".toml", ".json"):  # what every map reader refuses, a scene's with_map included
        raise BadInput(
            f"{flag} {path}: a settings file ({path.suffix}), not a map",
            hint="pass a map text file (.txt) of rows of # . S G (`cdrb envs --json` shows the stock maps' rows)",
        )
    text = read_input_text(path, flag, MAX_MAP_BYTES, "map file", "pass a text file of rows of # . S G")
    # the byte-order mark some Windows editors put first is not a map character (their \r\n ends lines as \n does)
    return parse_map(text.removeprefix("\ufeff"), name=path.stem, source=str(path))


def stock_layout(name: str) -> MazeLayout:
    text = resources.files("cdrb_cli.envs.pointmaze.maps").joinpath(f"{name}.txt").read_text()
    return parse_map(text, name=name, source=f"stock map {name}")


@lru_cache(maxsize=64)
def _has_pair(rows: tuple[str, ...]) -> bool:
    """Whether some start cell of ``rows`` reaches a goal cell other than itself (every artifact load of a map
    asks; the answer is kept per map)."""
    return MazeGeometry(MazeLayout.model_construct(name="", rows=list(rows))).has_start_goal_pair()


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

    def components(self) -> np.ndarray:
        """A label per cell of the free cell's 4-connected region (0, 1, ...); -1 on walls."""
        label = np.full(self.grid.shape, -1, dtype=np.int64)
        n = 0
        for cell in map(tuple, np.argwhere(self.free)):
            if label[cell] >= 0:
                continue
            label[cell] = n
            queue = deque([cell])
            while queue:
                for nb in self.neighbours(queue.popleft()):
                    if label[nb] < 0:
                        label[nb] = n
                        queue.append(nb)
            n += 1
        return label

    def has_start_goal_pair(self) -> bool:
        """Whether some start cell reaches a goal cell other than itself."""
        label = self.components()
        start_region, goal_region = label[tuple(self.start_cells.T)], label[tuple(self.goal_cells.T)]
        for c in np.unique(start_region):
            starts, goals = self.start_cells[start_region == c], self.goal_cells[goal_region == c]
            if len(goals) and (len(starts) > 1 or len(goals) > 1 or (starts[0] != goals[0]).any()):
                return True
        return False

    def grid_distances(self, sources, block: int = 256):
        """Grid distances (cells, 4-connected) from each source cell, a block of sources at a time: yields arrays
        (sources in the block, rows, cols), -1 where unreachable or a wall. :meth:`bfs` for many sources at once,
        in compiled code (a 100 x 100 map of start+goal cells asks 10,000 searches over 10,000 cells)."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import shortest_path

        index = np.full(self.grid.shape, -1, dtype=np.int64)
        n = int(self.free.sum())
        index[self.free] = np.arange(n)
        pairs = []
        for a, b in ((index[:, :-1], index[:, 1:]), (index[:-1, :], index[1:, :])):  # 4-connected neighbours
            both = (a >= 0) & (b >= 0)
            pairs.append(np.stack([a[both], b[both]]))
        edges = np.concatenate(pairs, axis=1)
        graph = coo_matrix((np.ones(edges.shape[1]), (edges[0], edges[1])), shape=(n, n)).tocsr()
        sources = index[tuple(np.asarray(sources, dtype=np.int64).reshape(-1, 2).T)]
        for k in range(0, len(sources), block):
            d = shortest_path(graph, directed=False, unweighted=True, indices=sources[k : k + block])
            out = np.full((len(d), *self.grid.shape), -1, dtype=np.int64)
            out[:, self.free] = np.where(np.isfinite(d), d, -1).astype(np.int64)
            yield out

    def longest_start_goal_path(self, anywhere: bool = False) -> int:
        """The largest grid distance (cells) from any start cell (``anywhere``: any free cell) to any goal cell
        reachable from it."""
        starts = tuple((np.argwhere(self.free) if anywhere else self.start_cells).T)
        return max([0, *(int(d[:, starts[0], starts[1]].max()) for d in self.grid_distances(self.goal_cells))])

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

    def bounds(self) -> tuple[list[float], list[float]]:
        """The map's outer edges, ([x low, y low], [x high, y high]) in metres: centred on the origin."""
        half_w, half_h = self.n_cols * self.s / 2, self.n_rows * self.s / 2
        return [-half_w, -half_h], [half_w, half_h]

    def obstacles(self, agent_radius: float) -> BoxObstacles:
        c, h = self.wall_boxes
        low, high = self.bounds()
        return BoxObstacles(
            dims=[0, 1],
            centers=c.round(9).tolist(),
            half_sizes=h.round(9).tolist(),
            inflate=agent_radius,
            low=low,
            high=high,
        )

    # -------------------------------------------------------------- protocol
    def draw_start_goal(self, rng: np.random.Generator, anywhere: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """A start cell and a different goal cell reachable from it, uniformly: the start from the layout's start
        cells (the protocol shared by collect and eval) or, ``anywhere``, from every free cell (plans from wherever
        the robot may be, to the protocol's goals)."""
        starts, goals = (np.argwhere(self.free) if anywhere else self.start_cells), self.goal_cells
        for _ in range(1000):  # rejection: uniform over the valid pairs, quick where most pairs are
            s = starts[int(rng.integers(len(starts)))]
            g = goals[int(rng.integers(len(goals)))]
            if (s != g).any() and self.bfs(g)[tuple(s)] >= 0:
                return s, g
        # few valid pairs (most start cells sealed off from the goals): the same distribution, drawn exactly
        valid = [
            (self.bfs(g)[starts[:, 0], starts[:, 1]] >= 0) & (starts != g).any(axis=1) for g in goals
        ]  # per goal, which starts reach it
        counts = np.array([v.sum() for v in valid], dtype=np.float64)
        if counts.sum() == 0:
            where = "free" if anywhere else "start"
            raise RunFailed(f"could not draw a start/goal pair: no goal cell is reachable from the {where} cells")
        gi = int(rng.choice(len(goals), p=counts / counts.sum()))
        s = starts[np.flatnonzero(valid[gi])[int(rng.integers(int(counts[gi])))]]
        return s, goals[gi]

    def detour_pairs(self, trained: MazeGeometry) -> np.ndarray:
        """Every (start cell, goal cell) pair of this map's protocol whose shortest path here is longer than in the
        ``trained`` map (a route the training map had is blocked), as rows (si, sj, gi, gj)."""
        out = []
        goals, si = self.goal_cells, tuple(self.start_cells.T)
        blocks = zip(self.grid_distances(goals), trained.grid_distances(goals))
        k = 0
        for here, before in blocks:
            a, b = here[:, si[0], si[1]], before[:, si[0], si[1]]  # (goals in the block, starts)
            for gi, si_ in zip(*np.nonzero((a >= 0) & ((b < 0) | (a > b)))):
                g, s = goals[k + gi], self.start_cells[si_]
                if (s != g).any():
                    out.append([*s, *g])
            k += len(here)
        return np.asarray(out, dtype=np.int64).reshape(-1, 4)

    def exit_label(self, states: np.ndarray) -> str:
        """The compass direction (from the start region's centre) of the first non-start cell a path enters."""
        starts = {tuple(c) for c in self.start_cells.tolist()}
        centre = self.start_cells.mean(axis=0)
        for cell in self.xy_to_cell(states[:, :2]):
            if tuple(cell.tolist()) not in starts:
                di, dj = cell - centre
                angle = np.arctan2(-di, dj)
                return _COMPASS[int(np.round(angle / (np.pi / 4))) % 8]
        return "none"


_COMPASS = ["E", "NE", "N", "NW", "W", "SW", "S", "SE"]
