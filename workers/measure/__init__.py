"""Front-ends that measure the walk: throughput (bench, behind ``bssrdf bench``), the efficiency
of the estimators (efficiency) and the cost of a renderer's table (table_cost)."""
