"""OGBench's PointMaze mazes: the stock maps and their geometry in OGBench's own coordinates.

OGBench (Park et al., ICLR 2025) lays a maze out on cells of ``MAZE_UNIT`` = 4 m: cell (i, j) has its centre at
x = 4 j - 4, y = 4 i - 4 (row i grows along y, so the map text printed top-down shows the maze upside down), and each
wall cell is a 4 x 4 m box. Keeping these coordinates makes a state here the same number as in an OGBench dataset.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from cdrb_cli.envs.pointmaze.maze import MazeGeometry, MazeLayout

MAZE_UNIT = 4.0
#: the world position of cell (0, 0)'s centre
ORIGIN = -4.0

#: the stock maps, row i = 0 first (y = -4), ``#`` a wall cell
MAPS = {
    "medium": [
        "########",
        "#..##..#",
        "#..#...#",
        "##...###",
        "#..#...#",
        "#.#..#.#",
        "#...#..#",
        "########",
    ],
    "large": [
        "############",
        "#....#.....#",
        "#.##.#.#.#.#",
        "#......#...#",
        "#.####.###.#",
        "#..#.#.....#",
        "##.#.#.#.###",
        "#..#...#...#",
        "############",
    ],
    "giant": [
        "################",
        "#.#......##....#",
        "#.#.##.#.#..##.#",
        "#...#..#...#...#",
        "#.###.######.#.#",
        "#...#...#....#.#",
        "###.#.#..#.#.###",
        "#...#..#...#...#",
        "#.#.#.######.#.#",
        "#.###...#...##.#",
        "#.....#...#....#",
        "################",
    ],
}

#: OGBench's five evaluation tasks per maze: (start cell, goal cell), as (i, j)
TASKS = {
    "medium": [((1, 1), (6, 6)), ((6, 1), (1, 6)), ((5, 3), (4, 2)), ((6, 5), (6, 1)), ((2, 6), (1, 1))],
    "large": [((1, 1), (7, 10)), ((5, 4), (7, 1)), ((7, 4), (1, 10)), ((3, 8), (5, 4)), ((1, 1), (5, 4))],
    "giant": [((1, 1), (10, 14)), ((1, 14), (10, 1)), ((8, 14), (1, 1)), ((8, 3), (5, 12)), ((5, 9), (3, 8))],
}


def layout(name: str) -> MazeLayout:
    """The stock map ``name`` as a layout (every free cell may start or end an episode)."""
    return MazeLayout(name=f"ogbench-{name}", rows=[r.replace(".", "C") for r in MAPS[name]], cell_size=MAZE_UNIT)


class OGBenchGeometry(MazeGeometry):
    """:class:`MazeGeometry` in OGBench's coordinates (cell centres at 4 j - 4, 4 i - 4; rows grow along y)."""

    def cell_to_xy(self, cells) -> np.ndarray:
        cells = np.asarray(cells, dtype=np.float64)
        return np.stack([cells[..., 1] * self.s + ORIGIN, cells[..., 0] * self.s + ORIGIN], axis=-1)

    def xy_to_cell(self, xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        j = np.floor((xy[..., 0] - ORIGIN) / self.s + 0.5)
        i = np.floor((xy[..., 1] - ORIGIN) / self.s + 0.5)
        return np.stack([i, j], axis=-1).astype(np.int64)

    def bounds(self) -> tuple[list[float], list[float]]:
        """The map's outer edges: from half a cell below cell (0, 0)'s centre."""
        low = ORIGIN - self.s / 2
        return [low, low], [low + self.n_cols * self.s, low + self.n_rows * self.s]

    @cached_property
    def vertex_cells(self) -> np.ndarray:
        """Free cells that are not straight corridor cells (free above and below with walls left and right, or the
        transpose): where OGBench's navigate data draws its goals."""
        out = []
        for i, j in np.argwhere(self.free):
            up, down = self.free[i - 1, j], self.free[i + 1, j]
            left, right = self.free[i, j - 1], self.free[i, j + 1]
            corridor = (up and down and not left and not right) or (left and right and not up and not down)
            if not corridor:
                out.append((i, j))
        return np.asarray(out, dtype=np.int64).reshape(-1, 2)

    def toward(self, cell, goal_cell) -> tuple[int, int]:
        """OGBench's oracle subgoal: of the current cell's four neighbours (in the order up, left, down, right by
        index: (-1, 0), (0, -1), (1, 0), (0, 1)), the first free one strictly closer to the goal by grid distance;
        the cell itself when none is."""
        dist = self.bfs_from(goal_cell)
        i, j = int(cell[0]), int(cell[1])
        best, here = (i, j), dist[i, j] if dist[i, j] >= 0 else np.inf
        for di, dj in ((-1, 0), (0, -1), (1, 0), (0, 1)):
            a, b = i + di, j + dj
            if 0 <= a < self.n_rows and 0 <= b < self.n_cols and self.free[a, b] and 0 <= dist[a, b] < here:
                best, here = (a, b), dist[a, b]
        return best

    def bfs_from(self, cell) -> np.ndarray:
        """:meth:`bfs` from ``cell``, computed once per cell (the expert asks every step, collection every episode)."""
        key = (int(cell[0]), int(cell[1]))
        cache = self.__dict__.setdefault("_bfs", {})
        if key not in cache:
            cache[key] = self.bfs(key)
        return cache[key]
