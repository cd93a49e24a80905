"""Evaluation: fly any policy on a split (:func:`rlplat.eval.episodes.evaluate`), per-episode
tables, statistics, plots, reports, comparisons and seed aggregation."""
