"""Alembic migrations of the job store; applied by :meth:`service.store.JobStore.migrate`."""
