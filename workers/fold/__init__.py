"""The fold: tallies and their error bars (tally, reweight), the deterministic merge of shards
(merge, sweep), the stopping rule on a result (target) and the tables (output, finite)."""
