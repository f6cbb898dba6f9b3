"""Pictures: stick-figure GIFs (one motion, or two side by side) and filmstrips, texton
timelines, and a self-contained HTML page with a 3-D player (``write_html``)."""

from ._compare import render_gif_pair as render_gif_pair
from ._gallery import (
    render_gallery as render_gallery,
    render_texton_gallery as render_texton_gallery,
    texton_instances as texton_instances,
)
from ._html import write_html as write_html
from ._plots import (
    plot_timeline as plot_timeline,
)
from ._quality import plot_speed_distributions as plot_speed_distributions
from ._render import render_filmstrip as render_filmstrip, render_gif as render_gif

__all__ = [
    "plot_speed_distributions",
    "plot_timeline",
    "render_filmstrip",
    "render_gallery",
    "render_gif",
    "render_gif_pair",
    "render_texton_gallery",
    "texton_instances",
    "write_html",
]
