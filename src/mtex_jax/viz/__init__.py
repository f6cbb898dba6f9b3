"""Pictures: stick-figure GIFs (one motion, or two side by side) and filmstrips, texton
timelines."""

from ._compare import render_gif_pair as render_gif_pair
from ._plots import (
    plot_timeline as plot_timeline,
)
from ._quality import plot_speed_distributions as plot_speed_distributions
from ._render import render_filmstrip as render_filmstrip, render_gif as render_gif

__all__ = [
    "plot_speed_distributions",
    "plot_timeline",
    "render_filmstrip",
    "render_gif",
    "render_gif_pair",
]
