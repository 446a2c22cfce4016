"""Plot helpers: each takes a matplotlib ``ax``, draws on it, and returns the artists it drew.

Nothing here creates a figure, changes global matplotlib state or shows a window.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.axes import Axes

    from iceg.grid import OccupancyGrid


def grid(ax: Axes, grid: OccupancyGrid, trajectory: ArrayLike | None = None) -> list[Artist]:
    """Draw an occupancy grid's probability map in metric world coordinates.

    Args:
        ax: The axes to draw on; its aspect is set equal and its axes labelled in metres.
        grid: The map; drawn as ``imshow(origin="lower", extent=grid.extent_xy)`` in grey
            (white free, black occupied, mid-grey unknown).
        trajectory: ``(N, 2+)`` world positions ``[x_m, y_m, ...]`` drawn as a red line,
            or ``None``.

    Returns:
        ``[image]`` or ``[image, trajectory_line]``.
    """
    image = ax.imshow(
        grid.probabilities(),
        cmap="gray_r",
        vmin=0.0,
        vmax=1.0,
        origin="lower",
        extent=grid.extent_xy,
        interpolation="nearest",
    )
    artists: list[Artist] = [image]
    if trajectory is not None:
        t = np.asarray(trajectory, dtype=np.float64)
        (line,) = ax.plot(t[:, 0], t[:, 1], color="tab:red", linewidth=1.0, label="trajectory")
        artists.append(line)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    return artists
