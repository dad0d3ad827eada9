"""Benchmarks of the service, apart from the product (not installed with the package; run from a
checkout, e.g. ``python -m bench.load``):

- :mod:`bench.queue`: claim and commit cost per shard on the job store (SQLite or PostgreSQL);
- :mod:`bench.load`: submissions and status reads against a real ``bssrdf serve`` with workers;
- :mod:`bench.fleet`: up to thousands of simulated workers on the claim path, direct or through
  a pooler (:mod:`bench.pooler` runs pgbouncer with ``deploy/pgbouncer/pgbouncer.ini``;
  :mod:`bench.fleet_report` forms its figures and its exactly-once check);
- :mod:`bench.merge`: merge memory against shard count;
- :mod:`bench.submit`: creation and deletion of the largest allowed job beside small submissions;
- :mod:`bench.run`: one job end to end;
- :mod:`bench.headers`: a client's latency while big request headers arrive.

The walk's own benchmarks are product commands in ``workers`` (``bssrdf bench``,
``python -m workers.measure.efficiency``, ``python -m workers.measure.table_cost``). Figures: BENCHMARKS.md.
"""
