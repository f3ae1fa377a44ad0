"""The paper's figures, drawn from cell records with matplotlib (Agg)."""

from vlaquantbench.figures.scope_recovery import ScopeRecoveryFigure, load_figure, plot_scope_recovery

__all__ = ["ScopeRecoveryFigure", "load_figure", "plot_scope_recovery"]
