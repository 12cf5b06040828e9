"""Checks that a figure explains itself: titles, labelled axes, a legend or colour bar, a caption."""
from matplotlib.figure import Figure
from matplotlib.legend import Legend
from matplotlib.text import Text


def texts(fig: Figure) -> list[str]:
    return [t.get_text() for t in fig.findobj(Text) if t.get_visible() and t.get_text()]


def caption(fig: Figure) -> str:
    """The longest text of the figure (its caption), on one line."""
    return " ".join(max(texts(fig), key=len).split())


def assert_explained(fig: Figure, *, min_caption: int = 150) -> None:
    panels = [ax for ax in fig.axes if ax.get_visible() and ax.get_label() != "<colorbar>"]
    assert panels, "no axes"
    for ax in panels:
        assert ax.get_title(), f"an axes has no title: {ax}"
        assert ax.get_xlabel() and ax.get_ylabel(), f"axes {ax.get_title()!r} lacks an axis label"
    legends = fig.findobj(Legend)
    colorbars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert legends or colorbars, "neither a legend nor a colour bar"
    assert all(len(legend.get_texts()) > 0 for legend in legends)
    assert len(caption(fig)) >= min_caption, f"no caption: {caption(fig)!r}"


def legend_labels(fig: Figure) -> list[str]:
    return [t.get_text() for legend in fig.findobj(Legend) for t in legend.get_texts()]
