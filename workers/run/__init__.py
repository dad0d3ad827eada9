"""Running shards: one shard's plan (plan), its run (shard), shards on worker processes (pool),
a whole spec on this machine (simulate)."""
