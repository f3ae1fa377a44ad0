"""Sub-commands of `vqb`; see `vlaquantbench.cli`."""
