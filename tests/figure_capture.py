"""The matplotlib figures a command saves, for tests of what a plot shows: a PNG's bytes
cannot say which axes, labels and markers it has."""

from __future__ import annotations

from typing import Any

import pytest
from matplotlib.figure import Figure


def saved_figures(monkeypatch: pytest.MonkeyPatch) -> list[Figure]:
    """Every Figure saved from now until the test ends, in order; each is still written."""
    saved: list[Figure] = []
    original = Figure.savefig

    def savefig(self: Figure, *args: Any, **kwargs: Any) -> None:
        saved.append(self)
        original(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", savefig)
    return saved


def legend_texts(fig: Figure) -> list[str]:
    """The legend entries of all the figure's axes, top to bottom."""
    return [t.get_text() for ax in fig.axes if (legend := ax.get_legend()) is not None
            for t in legend.get_texts()]
