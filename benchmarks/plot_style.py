"""One line style per meaning, in every picture of the docs (``docs/_ext/curves.py``) and of the plot scripts
(``plot_ppo``, ``plot_runs``):

- **solid, with markers**: what was measured (a run's evaluations, a pipeline's frames/s);
- **dashed, thinner**: the baseline it is compared against (the random policy of a learning curve,
  ManiSkill's gym path in a collection figure), in the colour of what it is the baseline of;
- **dotted, grey**: a reference level that was not measured (a success target, perfect scaling, an
  ideal, another project's figure).

Legends sit below the axes (:func:`legend_below`), never on the data.
"""

from __future__ import annotations

from typing import Any


def measured(i: int = 0, marker: str = "o") -> dict[str, Any]:
    return dict(color=f"C{i}", ls="-", lw=1.8, marker=marker, ms=5)


def baseline(i: int = 0, marker: str | None = None) -> dict[str, Any]:
    style = dict(color=f"C{i}", ls="--", lw=1.2)
    if marker is not None:
        style.update(marker=marker, ms=5)
    return style


def reference() -> dict[str, Any]:
    return dict(color="grey", ls=":", lw=1.4)


def legend_below(fig: Any, axes: list[Any], ncol: int = 2, fontsize: float = 9) -> Any:
    """One legend for ``axes`` (their labelled lines, each label once), centred below them; the axes are laid
    out above it."""
    handles, labels = [], []
    for ax in axes:
        for h, label in zip(*ax.get_legend_handles_labels()):
            if label not in labels:
                handles.append(h)
                labels.append(label)
    rows = -(-len(labels) // ncol)
    legend = fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=fontsize, frameon=False)
    bottom = (rows * fontsize * 1.7 / 72 + 0.12) / fig.get_size_inches()[1]  # the legend's rows, in inches
    fig.tight_layout(rect=(0, min(bottom, 0.45), 1, 1))
    return legend
