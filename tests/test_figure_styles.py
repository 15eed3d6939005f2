"""Readability of the report's charts: a distinct style per row however many rows, legends with every row of
every panel, and a log axis that one exploding model cannot flatten."""
from __future__ import annotations

import numpy as np

from denoisers.evaluate import MethodSpec
from denoisers.report.figures import LOG_AXIS_SPAN, _cut_log_axis, _styles, legend_entries, pyplot


def test_every_row_gets_its_own_colour_and_marker_pair() -> None:
    specs = [MethodSpec(f"row{i}", "noisy") for i in range(24)]     # the default config has 22 main rows
    styles = _styles(specs)
    pairs = {(tuple(style["color"]), style["marker"]) for style in styles.values()}
    assert len(pairs) == 24


def test_the_legend_holds_rows_that_only_some_panels_show() -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2)
    axes[0].plot([0, 1], [0, 1], label="a")
    axes[1].plot([0, 1], [1, 0], label="b")
    axes[1].plot([0, 1], [1, 1], label="a")
    _, labels = legend_entries(axes)
    plt.close(fig)
    assert labels == ["a", "b"]


def test_an_exploding_row_does_not_flatten_a_log_axis() -> None:
    plt = pyplot()
    fig, ax = plt.subplots()
    rows = [np.full(5, 0.01), np.full(5, 0.02), np.full(5, 1e7)]
    for values in rows:
        ax.plot(range(5), values)
    ax.set_yscale("log")
    _cut_log_axis(ax, rows)
    top = ax.get_ylim()[1]
    texts = [text.get_text() for text in ax.texts]
    plt.close(fig)
    assert top == LOG_AXIS_SPAN * 0.02      # the median of the row medians (0.01, 0.02, 1e7) is 0.02
    assert texts and "1e+07" in texts[0]
